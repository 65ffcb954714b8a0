"""One command that builds the reference policy: record demonstrations, train, then optionally a DAgger round.

    python -m reference_policies.pipeline --out models/octo-reference-robosuite --data data/reference_demos \
        [--dagger-episodes 64]

Stages: (1) scripted-expert demonstrations into `--data`; (2) behaviour cloning for `--steps`; with
`--dagger-episodes N`, (2) writes `<data>/stage1` and two more stages follow: (3) that checkpoint runs N
PickPlaceCan episodes and the state-based expert labels every state it visits (`reference_policies.dagger`,
into `<data>/dagger`); (4) fine-tuning from (2) on demonstrations + corrections for `--dagger-steps` at
`--dagger-learning-rate`, normalised with the demonstrations' statistics, into `--out`.

Everything is seeded (demonstration and episode seeds, batch sampling, initialisation, noise), so the same
command on the same software gives the same data and the same training runs. A recording or a collection
that already exists with the same configuration (and, for corrections, the same acting checkpoint) is
reused, and so is a finished stage 1 with the same training configuration and frame count; times are
reported from their summaries.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import asdict, replace
from pathlib import Path

from harness.files import atomic_write_json, read_json_object
from reference_policies import dagger
from reference_policies.demos import DemoConfig, existing_demos, load_demos, record_demos
from reference_policies.train import TrainConfig, train

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m reference_policies.pipeline", description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="models/octo-reference-robosuite", help="checkpoint folder to write")
    parser.add_argument("--data", default="data/reference_demos", help="folder for the recorded demonstrations (not committed)")
    parser.add_argument("--episodes", type=int, default=None,
                        help="demonstrations per task, the same for every task [Lift 96, Stack 128, PickPlaceCan 192]")
    parser.add_argument("--steps", type=int, default=TrainConfig.steps, help="training steps")
    parser.add_argument("--batch-size", type=int, default=TrainConfig.batch_size)
    parser.add_argument("--learning-rate", type=float, default=TrainConfig.learning_rate,
                        help="peak learning rate of the warm-up + cosine schedule")
    parser.add_argument("--workers", type=int, default=2, help="recording processes (spawned)")
    parser.add_argument("--seed", type=int, default=TrainConfig.seed, help="training seed")
    parser.add_argument("--dagger-episodes", type=int, default=0,
                        help="PickPlaceCan episodes of the trained policy to label for a DAgger round (0 = no round)")
    parser.add_argument("--dagger-steps", type=int, default=3000, help="fine-tuning steps of the DAgger round")
    parser.add_argument("--dagger-learning-rate", type=float, default=3e-4,
                        help="peak learning rate of the DAgger round")
    parser.add_argument("--init-from", default=None, metavar="CHECKPOINT",
                        help="warm start from this checkpoint folder (same architecture; patch-grid position embeddings "
                             "are resampled to the new image sizes) instead of random initialisation")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    for noisy in ("jax._src.xla_bridge", "robosuite_logs"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    if (args.episodes is not None and args.episodes < 4) or args.steps < 1 or args.batch_size < 1 \
            or not args.learning_rate > 0 or args.dagger_steps < 1 or not args.dagger_learning_rate > 0:
        parser.error("--episodes must be >= 4 (one per recording job), --steps, --dagger-steps and --batch-size "
                     ">= 1, learning rates > 0")
    dagger_config = None
    if args.dagger_episodes:
        if args.dagger_episodes < dagger.DaggerConfig.jobs:
            parser.error(f"--dagger-episodes must be 0 (no DAgger round) or >= {dagger.DaggerConfig.jobs} "
                         "(one per collection job)")
        dagger_config = dagger.DaggerConfig(episodes=args.dagger_episodes)

    start = time.perf_counter()
    train_config = TrainConfig(steps=args.steps, batch_size=args.batch_size, learning_rate=args.learning_rate,
                               seed=args.seed, init_from=args.init_from)
    demo_config = DemoConfig(image_sizes=train_config.image_sizes)
    if args.episodes is not None:
        demo_config = replace(demo_config, episodes=tuple((t, args.episodes) for t in demo_config.tasks))
    summary = existing_demos(demo_config, args.data)
    if summary is None:
        log.info("recording %s demonstrations into %s", dict(demo_config.episodes), args.data)
        summary = record_demos(demo_config, args.data, workers=args.workers)
    else:
        log.info("reusing the demonstrations in %s (recorded in %.0f s)", args.data, summary["seconds"])
    demos = load_demos(args.data, demo_config.tasks)
    if dagger_config is None:
        result = train(demos, args.out, train_config)
    else:
        result = dagger_round(
            demos, train_config, args.data, args.out,
            collect=lambda model, out: dagger.collect(model, out, dagger_config, workers=args.workers),
            existing=lambda model, out: dagger.existing(dagger_config, model, out),
            append=lambda d, out: dagger.append_corrections(d, out, dagger_config.task),
            steps=args.dagger_steps, learning_rate=args.dagger_learning_rate,
            what=f"{dagger_config.episodes} {dagger_config.task} episodes")
    result["demonstrations"] = summary
    result["pipeline_seconds_this_run"] = time.perf_counter() - start
    atomic_write_json(Path(args.out, "training_summary.json"), result, exact=True)
    log.info("done: %s (demonstrations %.0f s, training %.0f s)", args.out, summary["seconds"], result["total_seconds"])
    return 0


def dagger_round(demos: dict, train_config: TrainConfig, data_dir: str | Path, out: str | Path, *, collect, existing,
                 append, steps: int, learning_rate: float, what: str, train_kwargs: dict | None = None) -> dict:
    """Behaviour cloning into `<data_dir>/stage1`, then a DAgger round: that checkpoint acts and the expert labels
    the states it visits (`collect(model, out)` into `<data_dir>/dagger`, reused when `existing(model, out)` finds a
    finished one), then fine-tuning from stage 1 on demonstrations + corrections (`append(demos, out)`) for `steps`
    at peak `learning_rate`, with training seed + 1 and the demonstrations' normalisation, into `out`.
    Returns the fine-tuning summary with "stage1" and "dagger" added."""
    return dagger_rounds(demos, train_config, data_dir, out, rounds=1, collect=lambda model, folder, r: collect(model, folder),
                         existing=lambda model, folder, r: existing(model, folder), append=append, steps=steps,
                         learning_rate=learning_rate, what=what, train_kwargs=train_kwargs)


def dagger_rounds(demos: dict, train_config: TrainConfig, data_dir: str | Path, out: str | Path, *, rounds: int,
                  collect, existing, append, steps: int, learning_rate: float, what: str,
                  train_kwargs: dict | None = None, retrain: bool = False) -> dict:
    """Behaviour cloning into `<data_dir>/stage1`, then `rounds` DAgger rounds. Round r: the latest checkpoint
    (stage 1, then `<data_dir>/round<r-1>`) acts and the expert labels the states it visits (`collect(model, folder,
    r)` into `<data_dir>/dagger` for round 1 and `<data_dir>/dagger<r>` after; reused when `existing(model, folder,
    r)` finds a finished one), then fine-tuning from that checkpoint on the demonstrations + every round's
    corrections so far (`append(demos, folder)` each) for `steps` at peak `learning_rate`, with training seed + r and
    the demonstrations' normalisation, into `<data_dir>/round<r>` (the last round: into `out`). Every finished
    stage is reused, so a stopped build resumes at the stage it was in. `retrain`: each round trains anew instead,
    with `train_config` as stage 1 did (its steps, learning rate and warm start; seed + r), on the demonstrations +
    corrections, so the corrections are learnt together with everything else rather than by a fine-tuning that moves
    the whole policy (`steps` and `learning_rate` unused). Returns the last fine-tuning's summary with
    "stage1" and "dagger" (the last round's collection) and "rounds" (per round: collection and final loss)."""
    train_kwargs = train_kwargs or {}
    stage1 = Path(data_dir) / "stage1"
    first = finished_training(stage1, train_config, demos)
    if first is None:
        first = train(demos, stage1, train_config, **train_kwargs)
    else:
        log.info("reusing the stage-1 checkpoint in %s (trained in %.0f s)", stage1, first["train_seconds"])
    model, data, history, total = stage1, demos, [], first["total_seconds"]
    for r in range(1, rounds + 1):
        corrections = Path(data_dir) / ("dagger" if r == 1 else f"dagger{r}")
        collected = existing(model, corrections, r)
        if collected is None:
            log.info("DAgger round %d: %s of %s, labelled by the expert", r, what, model)
            collected = collect(model, corrections, r)
        else:
            log.info("reusing the corrections in %s (collected in %.0f s)", corrections, collected["seconds"])
        data = append(data, corrections)
        fine_tune = (replace(train_config, seed=train_config.seed + r) if retrain else
                     replace(train_config, steps=steps, learning_rate=learning_rate, seed=train_config.seed + r,
                             init_from=str(model)))
        target = Path(out) if r == rounds else Path(data_dir) / f"round{r}"
        result = finished_training(target, fine_tune, data) if r < rounds else None
        if result is None:
            result = train(data, target, fine_tune, normalise_with=demos, **train_kwargs)
        total += result["total_seconds"] + collected["seconds"]
        history.append({"round": r, "acted": str(model), "collection": collected, "final_loss": result.get("final_loss")})
        model = target
    result["stage1"] = {k: first.get(k) for k in ("frames", "train_seconds", "final_loss", "config", "warm_start")}
    result["dagger"] = collected
    result["rounds"] = history
    result["total_seconds"] = total
    return result


def finished_training(folder: Path, cfg: TrainConfig, demos: dict) -> dict | None:
    """The training summary in `folder` when a run with exactly `cfg` on as many frames as `demos` finished there."""
    summary = read_json_object(folder / "training_summary.json")
    if summary is None or not (folder / str(cfg.steps) / "default" / "checkpoint").is_file():
        return None
    frames = sum(len(arrays["action"]) for arrays in demos.values())
    if summary.get("config") != json.loads(json.dumps(asdict(cfg))) or summary.get("frames") != frames:
        return None
    return summary


if __name__ == "__main__":
    raise SystemExit(main())

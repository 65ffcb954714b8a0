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
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from harness.files import atomic_write_json, read_json_object
from harness.options import option
from reference_policies import dagger
from reference_policies.demos import DemoConfig, existing_demos, load_demos, record_demos
from reference_policies.options import Workers, add_options, parse, values
from reference_policies.train import TrainConfig, train

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineOptions:
    """The pipeline's own options; training's are `TrainConfig`'s fields, the recording processes `Workers`'."""
    out: str = option("models/octo-reference-robosuite", "--out", "checkpoint folder to write")
    data: str = option("data/reference_demos", "--data", "folder for the recorded demonstrations (not committed)")
    episodes: int | None = option(None, "--episodes", "demonstrations per task, the same for every task", type=int,
                                  default_text=", ".join(f"{task} {n}" for task, n in DemoConfig.episodes))
    dagger_episodes: int = option(0, "--dagger-episodes", "PickPlaceCan episodes of the trained policy to label for a "
                                                          "DAgger round (0 = no round)", type=int)
    dagger_steps: int = option(3000, "--dagger-steps", "fine-tuning steps of the DAgger round", type=int)
    dagger_learning_rate: float = option(3e-4, "--dagger-learning-rate", "peak learning rate of the DAgger round",
                                         type=float)

    def __post_init__(self) -> None:
        jobs = DemoConfig.jobs_per_task
        if (self.episodes is not None and self.episodes < jobs) or self.dagger_steps < 1 \
                or not self.dagger_learning_rate > 0:
            raise ValueError(f"--episodes must be >= {jobs} (one per recording job), --dagger-steps >= 1, "
                             "--dagger-learning-rate > 0")
        if self.dagger_episodes and self.dagger_episodes < dagger.DaggerConfig.jobs:
            raise ValueError(f"--dagger-episodes must be 0 (no DAgger round) or >= {dagger.DaggerConfig.jobs} "
                             "(one per collection job)")


def command_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m reference_policies.pipeline", description=__doc__.splitlines()[0])
    add_options(parser, (PipelineOptions, TrainConfig, Workers))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = command_parser()
    args, options = parse(parser, PipelineOptions, argv)
    try:
        train_config = TrainConfig(**values(TrainConfig, args))
        workers = Workers(**values(Workers, args)).workers
    except ValueError as e:
        parser.error(str(e))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    for noisy in ("jax._src.xla_bridge", "robosuite_logs"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    dagger_config = dagger.DaggerConfig(episodes=options.dagger_episodes) if options.dagger_episodes else None
    start = time.perf_counter()
    demo_config = DemoConfig(image_sizes=train_config.image_sizes)
    if options.episodes is not None:
        demo_config = replace(demo_config, episodes=tuple((t, options.episodes) for t in demo_config.tasks))
    summary = existing_demos(demo_config, options.data)
    if summary is None:
        log.info("recording %s demonstrations into %s", dict(demo_config.episodes), options.data)
        summary = record_demos(demo_config, options.data, workers=workers)
    else:
        log.info("reusing the demonstrations in %s (recorded in %.0f s)", options.data, summary["seconds"])
    demos = load_demos(options.data, demo_config.tasks)
    if dagger_config is None:
        result = train(demos, options.out, train_config)
    else:
        result = dagger_round(
            demos, train_config, options.data, options.out,
            collect=lambda model, out: dagger.collect(model, out, dagger_config, workers=workers),
            existing=lambda model, out: dagger.existing(dagger_config, model, out),
            append=lambda d, out: dagger.append_corrections(d, out, dagger_config.task),
            steps=options.dagger_steps, learning_rate=options.dagger_learning_rate,
            what=f"{dagger_config.episodes} {dagger_config.task} episodes")
    result["demonstrations"] = summary
    result["pipeline_seconds_this_run"] = time.perf_counter() - start
    atomic_write_json(Path(options.out, "training_summary.json"), result, exact=True)
    log.info("done: %s (demonstrations %.0f s, training %.0f s)", options.out, summary["seconds"], result["total_seconds"])
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

"""One command that builds the LIBERO-Object reference policy: record demonstrations, then train.

    python -m reference_policies.libero_pipeline --out models/octo-reference-libero-object \
        --data data/libero_object_demos [--recipe second] [--episodes N] [--steps N] [--init-from models/octo-reference-robosuite]
        [--dagger-episodes N --dagger-steps 1500]

(1) The scripted LIBERO-Object expert's demonstrations from sampled placements, never the suite's stored
evaluation states (reference_policies.libero_demos), into `--data`; (2) behaviour cloning with the robosuite
reference's trainer (reference_policies.train: the same Octo architecture, both cameras 128 px = 8x8 patches in the
second recipe (the first: wrist 64 px = 4x4), L1 head, frozen tiny T5 over a word vocabulary of the ten instructions and their
paraphrases), warm-started from `--init-from` (every parameter whose shape is unchanged), into `--out`, with a
harness.toml stating the LIBERO conventions (the "libero" action space, rot180 images, the cameras above).
With `--dagger-episodes N`, (2) writes `<data>/stage1`, which then runs N episodes per task from further sampled
placements while the state-based expert labels every state it visits (reference_policies.libero_dagger, into
`<data>/dagger`), and (3) fine-tunes from it on demonstrations + corrections (states near the grasp drawn more
often) into `--out`; `--dagger-rounds R` repeats (3) with each round's checkpoint acting (pipeline.dagger_rounds).
With `--dagger-retrain`, (3) trains anew as (2) did (its steps, learning rate and warm start) on demonstrations +
corrections instead of fine-tuning the acting checkpoint.
With `--missed-grasps P`, a demonstration's first close is, with probability P, a missed grasp the expert then
recovers from (libero_demos.MissConfig: the states where the reference stalls). With `--swaps N`, (1) also records
N swapped-instruction demonstrations per task into `<data>/swaps` (in a task's scene the expert picks another
task's named object that the scene holds; libero_demos.append_swaps files each under the task it named, so it trains
with that instruction): a layout then no longer tells which object to pick.
Everything is seeded, so the same command on the same machine gives the same data and weights; a finished
recording with the same configuration is reused.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from harness.files import atomic_write_json
from harness.options import option, shown
from reference_policies.libero_demos import (DEMONSTRATORS, LIBERO_CAMERAS, LiberoDemoConfig, MissConfig, append_swaps,
                                            existing_libero_demos, load_libero_demos, record_libero_demos)
from reference_policies import libero_dagger
from reference_policies.libero_dagger import LiberoDaggerConfig
from reference_policies.libero_expert import LiberoExpertConfig, name_values, with_radii
from reference_policies.options import Workers, add_options, parse, values
from reference_policies.pipeline import dagger_rounds
from reference_policies.train import TrainConfig, train

log = logging.getLogger(__name__)

DATASET_KEY = "libero_object_reference"
# the demonstrations of each recipe (docs/libero-reference.md): "first" made models/octo-reference-libero-object-first
# (commit 53c1e7a), "second" the reference models/octo-reference-libero-object
RECIPES = {
    "first": LiberoDemoConfig(episodes=20, jobs_per_task=2, demonstrator="timed", bursts=None,
                              cameras=(("image_primary", "agentview", 128), ("image_wrist", "robot0_eye_in_hand", 64))),
    "second": LiberoDemoConfig(),
}
DEFAULT_STEPS = 2500
RECIPE_STEPS = {"first": DEFAULT_STEPS, "second": 6000}  # as the robosuite reference (session 13 probed 5000)
# where each recipe's policy is committed: `--recipe first` without --out must not overwrite the reference
RECIPE_OUT = {"first": "models/octo-reference-libero-object-first", "second": "models/octo-reference-libero-object"}
DEFAULT_INIT = "models/octo-reference-robosuite"
DAGGER_STEPS, DAGGER_LEARNING_RATE = 1500, 3e-4  # a DAgger round's fine-tuning (without --dagger-retrain)


def conventions_toml(cameras=LIBERO_CAMERAS) -> str:
    """harness.toml of the LIBERO-Object reference policy (see harness.conventions)."""
    lines = ["# How octo-harness evaluates this checkpoint: trained on LIBERO-Object through the harness's LIBERO env",
             "# (libero action space: 6 OSC values in [-1, 1], gripper 1 open / 0 closed; rot180 images as OpenVLA's",
             "# LIBERO datasets hold them; cameras rendered at the model's sizes). Run it with --fast-render, as recorded.",
             'format = "octo-harness-conventions/1"', "",
             "[env]", 'action_space = "libero"', 'image_convention = "rot180"', "", "[env.cameras]"]
    lines += [f'{key} = ["{camera}", {size}]' for key, camera, size in cameras]
    lines += ["", "[policy]", f'dataset_key = "{DATASET_KEY}"', 'action_normalization = "normal"',
              'proprio_normalization = "normal"', ""]
    return "\n".join(lines)


def instructions(tasks: tuple[str, ...]) -> dict[str, tuple[str, ...]]:
    """{task: (instruction, paraphrases...)} from the LIBERO task table."""
    from envs.libero_tasks import get_libero_task

    return {t: (get_libero_task(t).instruction, *get_libero_task(t).paraphrases) for t in tasks}


def parse_task_weights(text: str, tasks: tuple[str, ...]) -> tuple[tuple[str, float], ...]:
    """"libero_object/0=3,libero_object/6=2" -> (("libero_object/0", 3.0), ("libero_object/6", 2.0)); every task named
    must be one the recipe trains on, every weight finite and > 0 (the others weigh 1)."""
    weights = []
    for item, task, sep, weight in name_values(text):
        if not sep or task not in tasks or not np.isfinite(weight) or weight <= 0:
            raise ValueError(f"--task-weights: {item!r} is not TASK=W with TASK one of {tasks[0]} .. {tasks[-1]} and "
                             "W > 0, e.g. libero_object/0=3")
        weights.append((task, weight))
    if len({t for t, _ in weights}) != len(weights):
        raise ValueError("--task-weights names a task twice")
    return tuple(weights)


def parse_tasks(text: str, tasks: tuple[str, ...]) -> tuple[str, ...]:
    """"libero_object/0,libero_object/6" -> those tasks in the recipe's order; "" -> every task of the recipe."""
    named = [part.strip() for part in text.split(",") if part.strip()]
    unknown = [t for t in named if t not in tasks]
    if unknown:
        raise ValueError(f"--dagger-tasks: {unknown[0]!r} is not a task of the recipe ({tasks[0]} .. {tasks[-1]})")
    return tuple(t for t in tasks if t in named) if named else tuple(tasks)


def _recipes(values: dict) -> str:
    return ", ".join(f"{recipe} {value}" for recipe, value in values.items())


@dataclass(frozen=True)
class LiberoPipelineOptions:
    """The LIBERO pipeline's own options (each field's check in `__post_init__`; those that need the recipe in
    `_checked`); training's batch size, learning rate and seed are `TrainConfig`'s fields, the processes `Workers`'."""
    out: str | None = option(None, "--out", "checkpoint folder to write",
                             default_text="the recipe's committed folder: " + _recipes(RECIPE_OUT))
    data: str = option("data/libero_object_demos", "--data", "folder for the demonstrations (not committed)")
    recipe: str = option("second", "--recipe", "first: the committed checkpoint's demonstrations (timed expert, wrist "
                         "64 px, 20 a task, Gaussian noise only); second: issue 46's (state expert, wrist 128 px, 50 a "
                         "task, recovery bursts)", choices=tuple(sorted(RECIPES)))
    episodes: int | None = option(None, "--episodes", "demonstrations per task", type=int, default_text="the recipe's")
    steps: int | None = option(None, "--steps", "training steps", type=int,
                               default_text="the recipe's: " + _recipes(RECIPE_STEPS))
    demonstrator: str | None = option(None, "--demonstrator", "timed: the phase expert (12-step close); state: the "
                                      "state-based expert, which lifts once the fingers hold the object",
                                      choices=tuple(sorted(DEMONSTRATORS)), default_text="the recipe's")
    close_below_top: float | None = option(None, "--close-below-top", "the state-based demonstrator closes only with "
                                           "the hand this far below the object's top (a flat object's grasp)",
                                           type=float, metavar="METRES", default_text="no limit")
    demonstrator_radii: str = option("", "--demonstrator-radii", "the state-based demonstrator's radii (centred, "
                                     "at_grasp, grasp_height; the DAgger labeller keeps its own), e.g. "
                                     "grasp_height=0.004 to close only near the grasp height",
                                     metavar="NAME=METRES,...", default_text="LiberoExpertConfig's")
    missed_grasps: float | None = option(None, "--missed-grasps", "with probability P a demonstration's first grasp is "
                                         "missed (driven 3 cm beside the object, it closes there) and the expert "
                                         "recovers (libero_demos.MissConfig)", type=float, metavar="P",
                                         default_text="none")
    swaps: int = option(0, "--swaps", "also N swapped-instruction demonstrations per task (into <data>/swaps): in its "
                        "scene the expert picks another task's named object, under that task's instruction", type=int,
                        metavar="N")
    dagger_episodes: int = option(0, "--dagger-episodes", "episodes per task of the trained policy to label for a "
                                  "DAgger round (0 = no round)", type=int)
    dagger_tasks: str = option("", "--dagger-tasks", "the tasks a DAgger round collects on (e.g. "
                               "libero_object/0,libero_object/6)", metavar="TASK,...", default_text="every task")
    dagger_close_below_top: float | None = option(None, "--dagger-close-below-top", "the DAgger labeller closes only "
                                                  "with the hand this far below the object's top", type=float,
                                                  metavar="METRES",
                                                  default_text="--close-below-top's: the demonstrator's")
    # None until given, so --dagger-retrain can refuse it; the default is the table's (DAGGER_STEPS)
    dagger_steps: int | None = option(None, "--dagger-steps", "fine-tuning steps of each DAgger round", type=int,
                                      default_text=shown(DAGGER_STEPS))
    dagger_rounds: int = option(1, "--dagger-rounds", "DAgger rounds, each acting with the previous round's "
                                "checkpoint", type=int)
    dagger_learning_rate: float | None = option(None, "--dagger-learning-rate", "peak learning rate of the DAgger "
                                                "round's fine-tuning", type=float,
                                                default_text=shown(DAGGER_LEARNING_RATE))
    dagger_retrain: bool = option(False, "--dagger-retrain", "each DAgger round trains anew on demonstrations + "
                                  "corrections, as stage 1 did (--steps, --learning-rate, --init-from), instead of "
                                  "fine-tuning the acting checkpoint", action="store_true")
    task_weights: str = option("", "--task-weights", "batches draw these tasks W times as often as the others (e.g. "
                               "libero_object/0=3)", metavar="TASK=W,...", default_text="none")
    init_from: str = option(DEFAULT_INIT, "--init-from", "warm start from this checkpoint folder ('none': random "
                            "initialisation)", metavar="CHECKPOINT")

    def __post_init__(self) -> None:
        if self.dagger_retrain and (self.dagger_steps is not None or self.dagger_learning_rate is not None):
            raise ValueError("--dagger-retrain trains each round with --steps and --learning-rate: leave out "
                             "--dagger-steps and --dagger-learning-rate (they set a fine-tuning)")
        if self.dagger_retrain and not self.dagger_episodes:
            raise ValueError("--dagger-retrain sets how a DAgger round trains: give it with --dagger-episodes N")
        if (self.episodes is not None and self.episodes < 2) or (self.steps is not None and self.steps < 1) \
                or (self.dagger_steps is not None and self.dagger_steps < 1) \
                or (self.dagger_learning_rate is not None and not self.dagger_learning_rate > 0) \
                or not 1 <= self.dagger_rounds <= 9 or not 0 <= self.swaps <= 1000:
            raise ValueError("--episodes must be >= 2, --steps and --dagger-steps >= 1, learning rates > 0, "
                             "--dagger-rounds 1..9, --swaps 0..1000")
        for flag, value in (("--close-below-top", self.close_below_top),
                            ("--dagger-close-below-top", self.dagger_close_below_top)):
            if value is not None and not 0 <= value < 0.05:
                raise ValueError(f"{flag} must be at least 0 and under 0.05 (metres)")
        if self.missed_grasps is not None and not 0 < self.missed_grasps <= 1:
            raise ValueError(f"--missed-grasps {self.missed_grasps}: a probability in (0, 1], e.g. 0.5")


def command_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m reference_policies.libero_pipeline",
                                     description=__doc__.splitlines()[0])
    add_options(parser, (LiberoPipelineOptions,))
    add_options(parser, (TrainConfig,), only=("batch_size", "learning_rate", "seed"))
    add_options(parser, (Workers,))
    return parser


def _checked(parser: argparse.ArgumentParser, argv: list[str] | None):
    """(args, task weights, DAgger configuration or None, warm-start folder or None); a bad value is the parser's
    one-line error (exit 2) before anything loads. `args` holds every option's value, defaults filled in."""
    given, options = parse(parser, LiberoPipelineOptions, argv)
    try:
        training = TrainConfig(**values(TrainConfig, given, skip=("steps", "init_from")))
        workers = Workers(**values(Workers, given))
    except ValueError as e:
        parser.error(str(e))
    args = argparse.Namespace(**asdict(options), **asdict(workers), batch_size=training.batch_size,
                              learning_rate=training.learning_rate, seed=training.seed)
    args.steps = RECIPE_STEPS[args.recipe] if args.steps is None else args.steps
    args.out = RECIPE_OUT[args.recipe] if args.out is None else args.out
    args.dagger_steps = DAGGER_STEPS if args.dagger_steps is None else args.dagger_steps
    args.dagger_learning_rate = DAGGER_LEARNING_RATE if args.dagger_learning_rate is None else args.dagger_learning_rate
    try:
        task_weights = parse_task_weights(args.task_weights, RECIPES[args.recipe].tasks)
        for option, value in (("--close-below-top", args.close_below_top), ("--demonstrator-radii", args.demonstrator_radii)):
            if value not in (None, "") and (args.demonstrator or RECIPES[args.recipe].demonstrator) != "state":
                raise ValueError(f"{option} is the state-based demonstrator's: use --demonstrator state")
        args.bursts = RECIPES[args.recipe].bursts
        if args.missed_grasps is not None:
            if args.bursts is None:
                raise ValueError(f"--missed-grasps adds to the recovery bursts, which the {args.recipe} recipe has none of")
            if (args.demonstrator or RECIPES[args.recipe].demonstrator) != "state":
                raise ValueError("--missed-grasps needs the state-based demonstrator (--demonstrator state): the timed "
                                 "one follows its own clock and cannot recover from a grasp it did not make")
            args.bursts = replace(args.bursts, miss=MissConfig(rate=args.missed_grasps))
        args.demonstrator_expert = with_radii(args.demonstrator_radii,
                                              replace(RECIPES[args.recipe].expert, close_below_top=args.close_below_top),
                                              "--demonstrator-radii")
    except ValueError as e:
        parser.error(str(e))
    dagger_config = None
    if args.dagger_episodes:
        try:
            dagger_config = LiberoDaggerConfig(episodes=args.dagger_episodes,
                                               tasks=parse_tasks(args.dagger_tasks, RECIPES[args.recipe].tasks),
                                               expert=LiberoExpertConfig(close_below_top=args.close_below_top
                                                                         if args.dagger_close_below_top is None
                                                                         else args.dagger_close_below_top))
        except ValueError as e:
            parser.error(str(e))
    init = None if args.init_from.lower() == "none" else args.init_from
    if init is not None and not (Path(init) / "config.json").is_file():
        parser.error(f"--init-from {init}: no checkpoint there (a folder with config.json); use 'none' to train "
                     "from scratch")
    return args, task_weights, dagger_config, init


def main(argv: list[str] | None = None) -> int:
    args, task_weights, dagger_config, init = _checked(command_parser(), argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    for noisy in ("jax._src.xla_bridge", "robosuite_logs"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    start = time.perf_counter()
    demo_config = RECIPES[args.recipe]
    demo_config = replace(demo_config, episodes=args.episodes or demo_config.episodes,
                          demonstrator=args.demonstrator or demo_config.demonstrator,
                          expert=args.demonstrator_expert, bursts=args.bursts)
    summary = existing_libero_demos(demo_config, args.data)
    if summary is None:
        log.info("recording %d demonstrations per task into %s", demo_config.episodes, args.data)
        summary = record_libero_demos(demo_config, args.data, workers=args.workers)
    else:
        log.info("reusing the demonstrations in %s (recorded in %.0f s)", args.data, summary["seconds"])
    demos = load_libero_demos(args.data, demo_config.tasks)
    if args.swaps:
        swap_config, swap_dir = replace(demo_config, episodes=args.swaps, swaps=True), Path(args.data, "swaps")
        swapped = existing_libero_demos(swap_config, swap_dir)
        if swapped is None:
            log.info("recording %d swapped-instruction demonstrations per task into %s", args.swaps, swap_dir)
            swapped = record_libero_demos(swap_config, swap_dir, workers=args.workers)
        summary = {**summary, "swaps": swapped}
        demos = append_swaps(demos, swap_dir, demo_config.tasks)
    train_config = replace(TrainConfig(), steps=args.steps, batch_size=args.batch_size, learning_rate=args.learning_rate,
                           seed=args.seed, init_from=init, task_weights=task_weights,
                           image_sizes=tuple((k, s) for k, _, s in demo_config.cameras))
    train_kwargs = {"instructions": instructions(demo_config.tasks), "dataset_key": DATASET_KEY,
                    "conventions": conventions_toml(demo_config.cameras)}
    if dagger_config is None:
        result = train(demos, args.out, train_config, **train_kwargs)
    else:
        of_round = lambda r: replace(dagger_config, round=r)  # noqa: E731
        result = dagger_rounds(
            demos, train_config, args.data, args.out, rounds=args.dagger_rounds,
            collect=lambda model, out, r: libero_dagger.collect(model, out, of_round(r), workers=args.workers),
            existing=lambda model, out, r: libero_dagger.existing(of_round(r), model, out),
            append=lambda d, out: libero_dagger.append_all(d, out, dagger_config.tasks),
            steps=args.dagger_steps, learning_rate=args.dagger_learning_rate, retrain=args.dagger_retrain,
            what=f"{dagger_config.episodes} episodes on each of {len(dagger_config.tasks)} tasks", train_kwargs=train_kwargs)
    result["demonstrations"] = summary
    result["pipeline_seconds_this_run"] = time.perf_counter() - start
    atomic_write_json(Path(args.out, "training_summary.json"), result, exact=True)
    log.info("done: %s (demonstrations %.0f s, swapped-instruction demonstrations %.0f s, training %.0f s)", args.out,
             summary["seconds"], summary.get("swaps", {}).get("seconds", 0.0), result["total_seconds"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""`octo-harness robustness`: a grid of perturbation kinds x levels x tasks, one run folder per condition.

Its run options are `run`'s own fields (harness.run.settings.RUN_OPTIONS); only where the grid differs is stated
here: model, task and kinds are required, 20 episodes, no overlay PNGs."""

from __future__ import annotations

from pathlib import Path

from harness.cli.common import add_execution_args
from harness.options import add_arguments

SHARED = ("model", "task", "perturb")  # run's options the grid requires
MODEL = ("text_tokenizer", "served_conventions")  # how the model is loaded: a checkpoint's tokenizer, a server's keys
SETTINGS = ("episodes", "seed", "max_steps")  # run's options each run of the grid takes
OUTPUTS = ("fast_render", "png_every", "no_video")
# the per-step measures each run of the grid may add (they never change actions): position controls, region reliance,
# and the failure signals (readout features, action consistency: issue 74)
MEASURES = ("attention_controls", "controls_every", "reliance_every", "reliance_fill", "readout_features_every",
            "action_consistency", "action_samples")
DIFFERS = {"model": {"required": True}, "task": {"required": True},
           "perturb": {"required": True, "metavar": "KINDS"},  # kinds only: the grid sets the levels
           "episodes": {"default": 20},
           "png_every": {"default": 0}}


def add_parser(sub) -> None:
    from harness.run.settings import RUN_OPTIONS

    classes = [cls for cls, _ in RUN_OPTIONS]
    rob = sub.add_parser("robustness", help="run a grid of perturbation kinds x levels x tasks into one folder of runs",
                         description="One run per (kind, level > 0) over every task, plus one nominal run for level 0 "
                                     "(docs/perturbations.md); resumable: the same command finishes what is missing. "
                                     "`octo-harness report OUT/*/` then adds a Robustness section.")
    add_arguments(rob, classes, "robustness", only=SHARED, overrides=DIFFERS)
    add_arguments(rob, classes, "robustness", only=MODEL, overrides=DIFFERS)
    rob.add_argument("--levels", default="0,1,3,5", help="comma-separated levels 0-5 (0 = the nominal run) [0,1,3,5]")
    add_arguments(rob, classes, "robustness", only=SETTINGS, overrides=DIFFERS)
    rob.add_argument("--out", type=Path, default=Path("results/robustness"), help="grid folder [results/robustness]")
    rob.add_argument("--protocol", type=Path, default=None, help="TOML protocol file for every other run setting")
    add_arguments(rob, classes, "robustness", only=OUTPUTS, overrides=DIFFERS)
    add_arguments(rob, classes, "robustness", only=MEASURES, overrides=DIFFERS)
    rob.add_argument("--overwrite", action="store_true", help="start every run of the grid afresh")
    add_execution_args(rob)
    rob.set_defaults(func=main)


def grid_protocol(args):
    """The protocol every run of the grid shares (before each run's perturbation): the protocol file, then the flags."""
    from harness.run.settings import build_protocol, read_protocol_file

    given = {key: getattr(args, key) for key in ("model", "task", *MODEL, *SETTINGS, *OUTPUTS, *MEASURES)}
    settings = {**(read_protocol_file(args.protocol) if args.protocol else {}),
                **{k: v for k, v in given.items() if v is not None}}
    if settings.get("perturb"):
        raise ValueError("the grid sets each run's perturbation; drop perturb from the protocol file")
    return build_protocol(settings)


def main(args) -> int:
    from harness.cli.common import execution
    from harness.gate.robustness import parse_kinds, parse_levels, run_grid

    conditions, levels = parse_kinds(args.perturb), parse_levels(args.levels)
    factory = execution(args)
    summaries = run_grid(grid_protocol(args), conditions, levels, args.out, executor=factory,
                         overwrite=args.overwrite)
    for name, summary in summaries.items():
        s = summary.statistics["overall"]
        print(f"{name:<28} {summary.status:<12} {s['successes']}/{s['n']} successes, {s['failed']} errored")
    print(f"robustness: {args.out} (report: octo-harness report {args.out}/*/ --out {args.out}/report)")
    return 0 if all(s.status == "complete" for s in summaries.values()) else 1

"""`octo-harness compare`: the paired verdict of a candidate run (or grid) against a baseline (same seeds)."""

from __future__ import annotations

from pathlib import Path

from harness.cli.common import add_gate_options, add_render_arg, writing


def add_parser(sub) -> None:
    cmp_ = sub.add_parser("compare", help="paired verdict of a candidate run against a baseline run (same seeds)",
                          description="Pair episodes by (task, seed); write compare.json, compare.md and compare.html. "
                                      "Exit 0 pass, 1 REGRESSED or SUSPECT (see --fail-on), 2 incompatible or invalid "
                                      "input, or outputs that could not be written, 3 ERRORED (an arm errored on more "
                                      "than half of its paired episodes), 4 INCOMPLETE (the candidate lacks episodes "
                                      "the baseline finished).")
    cmp_.add_argument("baseline", type=Path, metavar="BASELINE_RUN",
                      help="baseline run folder, or a robustness grid folder (octo-harness robustness): then every "
                           "task x condition is one cell of the Holm family, so one lost condition fails the gate")
    cmp_.add_argument("candidate", type=Path, metavar="CANDIDATE_RUN", help="candidate run (or grid) folder")
    add_gate_options(cmp_, "compare", ("max_drop", "alpha", "first_steps", "fail_on"))
    cmp_.add_argument("--out", type=Path, default=None, help="output folder [CANDIDATE_RUN/compare_<baseline name>]")
    cmp_.add_argument("--no-frames", action="store_true", help="do not render step-0 camera frames for the overlays")
    add_render_arg(cmp_)
    cmp_.set_defaults(func=main)


def main(args) -> int:
    from harness.analysis.compare import compare_grids, compare_runs, exit_code, is_grid
    from harness.gate.config import GateConfig
    from harness.report.compare_html import step0_frames, write_comparison

    gate = GateConfig.from_args(args)
    config = gate.compare()
    if is_grid(args.baseline) != is_grid(args.candidate):
        raise ValueError("compare two robustness grid folders (octo-harness robustness) or two run folders, not one of "
                         "each")
    grid = is_grid(args.baseline)
    result = (compare_grids if grid else compare_runs)(args.baseline, args.candidate, config)
    code = exit_code(result, gate.fail_on)
    frames = {} if args.no_frames or result.env is None else step0_frames(result, result.env)
    out = args.out or (args.candidate / f"compare_{args.baseline.resolve().name}" if grid else
                       Path(result.candidate.path) / f"compare_{result.baseline.run}")
    paths = writing(f"compare's outputs in {out}", result.verdict, lambda: write_comparison(result, out, frames, code))
    print(paths["markdown"].read_text(), end="")
    print(f"compare: {paths['html']}")
    return code

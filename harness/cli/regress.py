"""`octo-harness regress`: a candidate model on a baseline run's (or grid's) protocol and seeds until a sequential
test decides."""

from __future__ import annotations

import sys
from pathlib import Path

from harness.cli.common import add_execution_args, add_gate_options, add_render_arg, add_verbose, execution, writing


def add_parser(sub) -> None:
    reg = sub.add_parser("regress", help="run a candidate on a baseline's protocol and seeds until a sequential test decides",
                         description="Pair by pair (round by round over tasks) through the run store (resumable); "
                                     "one anytime-valid test per task (alpha / tasks each); stops as soon as a task "
                                     "regressed or every task decided. Exit codes as for compare, from the worse "
                                     "of the sequential verdict and compare's verdict on the pairs run.")
    reg.add_argument("--baseline", type=Path, required=True, metavar="RUN",
                     help="baseline run folder, or a robustness grid folder: each condition's sequential test then runs "
                          "at alpha / conditions, and the pairs are compared as a grid")
    reg.add_argument("--model", required=True, help="candidate model (as for `run --model`)")
    add_gate_options(reg, "regress", ("max_episodes", "max_drop", "alpha"))
    reg.add_argument("--out", type=Path, default=Path("results/runs"), help="output root of the candidate run [results/runs]")
    reg.add_argument("--run-name", default=None, help="candidate run folder name [<model>_<protocol hash>]")
    add_gate_options(reg, "regress", ("fail_on",))
    add_verbose(reg)
    add_gate_options(reg, "regress", ("text_tokenizer", "drop_probes"))
    add_execution_args(reg)
    add_render_arg(reg)
    reg.set_defaults(func=main)


def main(args) -> int:
    from harness.analysis.compare import is_grid
    from harness.gate.config import GateConfig
    from harness.report.compare_html import write_comparison
    from harness.gate.regress import exit_code, regress, write_regress

    factory = execution(args)
    gate = GateConfig.from_args(args)
    if is_grid(args.baseline):  # a robustness grid: condition by condition, Holm over every task x condition
        from harness.gate.regress import grid_fail_on, regress_grid

        fail_on, note = grid_fail_on(gate.fail_on)
        if note:
            print(note, file=sys.stderr)
        result = regress_grid(args.baseline, args.model, gate, out=args.out, run_name=args.run_name, executor=factory)
        code = exit_code(result, fail_on)
        paths = write_regress(result, code, write_comparison)
        print(paths["summary"])
        print(f"regress: {paths['json']}")
        return code
    result = regress(args.baseline, args.model, gate, out=args.out, run_name=args.run_name, executor=factory)
    code = exit_code(result, gate.fail_on)
    paths = writing(f"regress's outputs in {result.candidate_run}/regress", result.verdict,
                    lambda: write_regress(result, code, write_comparison))
    print(paths["summary"])
    print(f"regress: {paths['json']}")
    return code

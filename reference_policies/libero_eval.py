"""Helpers of scripts/evaluate_libero_reference.sh: the instruction swaps of LIBERO-Object and a nonsense instruction.

    python -m reference_policies.libero_eval swaps      # "<task>\t<swapped instruction>" per task
    python -m reference_policies.libero_eval nonsense   # the nonsense instruction
    python -m reference_policies.libero_eval closed-loop RANDOM_RUN TOP_RUN --eval-md EVAL.md   # paired table

A swap tells scene task i the instruction of task j, where j is the next task (i+1, i+2, ... mod 10) whose named
object is also in scene i, so the swapped instruction names an object the policy can pick. The scenes' objects are
read from LIBERO (an env without cameras per task).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

from harness.options import option
from reference_policies.libero_demos import LIBERO_OBJECT_TASKS
from reference_policies.options import Provenance, add_options, values

NONSENSE = "blorp the zizzle and fleem it quantum"  # no word of the model's vocabulary: a language-blind probe


def scene_objects(task: str) -> list[str]:
    import envs

    env = envs.make(task, cameras={})
    try:
        return list(env.description.get("movable", env.description["objects"]))
    finally:
        env.close()


def swaps(tasks: tuple[str, ...] = LIBERO_OBJECT_TASKS) -> dict[str, str]:
    """{scene task: the instruction of the next task whose named object the scene also holds}."""
    from envs.libero_tasks import get_libero_task
    from reference_policies.libero_demos import evaluation_swap

    out = {}
    for task in tasks:
        other = evaluation_swap(task, scene_objects(task), tasks)
        if other is not None:
            out[task] = get_libero_task(other).instruction
    return out


CLOSED_LOOP = "## Closed loop: masking what the policy looks at"


def closed_loop_markdown(records, note: str = "") -> str:
    """EVAL.md section: per task, successes with mask-random and with mask-top from the same initial states, the
    discordant pairs and an exact two-sided McNemar test (binomial on the discordant pairs); then all tasks pooled.
    `records`: the mask-random run's and the mask-top run's (harness.analysis.runs.load_run)."""
    from scipy.stats import binomtest

    from harness.measures.stats import wilson_interval

    outcome = [{(e.task, e.seed): bool(e.success) for e in r.episodes if e.ok} for r in records]
    pairs = sorted(set(outcome[0]) & set(outcome[1]))
    spec = [str(((r.manifest.get("protocol") or {}).get("policy") or {}).get("intervention")) for r in records]
    lines = [CLOSED_LOOP, ""] + ([note, ""] if note else [])
    lines += [f"Paired by (task, initial state): `{spec[0]}` against `{spec[1]}`, {len(pairs)} pairs.", "",
              "| task | pairs | mask-random | mask-top | only mask-random succeeded | only mask-top succeeded | "
              "McNemar exact p |", "|---|---|---|---|---|---|---|"]
    tasks = list(dict.fromkeys(t for t, _ in pairs))
    for task in tasks + ["all"]:
        keys = [k for k in pairs if task in ("all", k[0])]
        a = [outcome[0][k] for k in keys]
        b = [outcome[1][k] for k in keys]
        only_a = sum(x and not y for x, y in zip(a, b))
        only_b = sum(y and not x for x, y in zip(a, b))
        p = binomtest(only_a, only_a + only_b).pvalue if only_a + only_b else 1.0
        cells = []
        for xs in (a, b):
            low, high = wilson_interval(sum(xs), len(xs))
            cells.append(f"{sum(xs)}/{len(xs)} [{low:.2f}, {high:.2f}]")
        name = "**all tasks**" if task == "all" else task
        lines.append(f"| {name} | {len(keys)} | {cells[0]} | {cells[1]} | {only_a} | {only_b} | {p:.3g} |")
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class ClosedLoopOptions:
    eval_md: str = option(flag="--eval-md", help="the EVAL.md whose closed-loop section is written")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m reference_policies.libero_eval", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="action", required=True)  # not "command": closed-loop has a --command option
    sub.add_parser("swaps", help="print '<task>\\t<swapped instruction>' per LIBERO-Object task")
    sub.add_parser("nonsense", help="print the nonsense instruction")
    closed = sub.add_parser("closed-loop", help="write EVAL.md's closed-loop section from a mask-random and a "
                                                "mask-top run")
    closed.add_argument("random_run")
    closed.add_argument("top_run")
    add_options(closed, (ClosedLoopOptions, Provenance))
    args = parser.parse_args(argv)
    if args.action == "closed-loop":
        from harness.analysis.provenance import command_text, provenance_line
        from harness.analysis.runs import load_run
        from harness.report.eval_md import write_section

        made = Provenance(**values(Provenance, args))
        records = [load_run(args.random_run), load_run(args.top_run)]  # each run read once
        text = closed_loop_markdown(records, made.note)
        command = made.command or command_text("python -m reference_policies.libero_eval closed-loop",
                                               [args.random_run, args.top_run], ["--eval-md", args.eval_md])
        print(write_section(args.eval_md, text, provenance_line(command, [r.manifest for r in records])))
    elif args.action == "swaps":
        for task, instruction in swaps().items():
            print(f"{task}\t{instruction}")
    else:
        print(NONSENSE)
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

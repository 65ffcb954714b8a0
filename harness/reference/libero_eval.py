"""Helpers of scripts/evaluate_libero_reference.sh: the instruction swaps of LIBERO-Object and a nonsense instruction.

    python -m harness.reference.libero_eval swaps      # "<task>\t<swapped instruction>" per task
    python -m harness.reference.libero_eval nonsense   # the nonsense instruction

A swap tells scene task i the instruction of task j, where j is the next task (i+1, i+2, ... mod 10) whose named
object is also in scene i, so the swapped instruction names an object the policy can pick. The scenes' objects are
read from LIBERO (an env without cameras per task).
"""

from __future__ import annotations

import argparse
import sys

from harness.reference.libero_demos import LIBERO_OBJECT_TASKS

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

    specs = [get_libero_task(t) for t in tasks]
    out = {}
    for i, spec in enumerate(specs):
        objects = set(scene_objects(spec.name))
        for step in range(1, len(specs)):
            other = specs[(i + step) % len(specs)]
            if other.targets[0] in objects:
                out[spec.name] = other.instruction
                break
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m harness.reference.libero_eval", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("swaps", help="print '<task>\\t<swapped instruction>' per LIBERO-Object task")
    sub.add_parser("nonsense", help="print the nonsense instruction")
    args = parser.parse_args(argv)
    if args.command == "swaps":
        for task, instruction in swaps().items():
            print(f"{task}\t{instruction}")
    else:
        print(NONSENSE)
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

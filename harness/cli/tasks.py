"""`octo-harness tasks`: the registered robosuite and LIBERO tasks and their instructions."""

from __future__ import annotations


def add_parser(sub) -> None:
    sub.add_parser("tasks", help="list the registered tasks").set_defaults(func=main)


def main(args) -> int:
    import envs

    print(envs.task_table(all_suites=True))
    print(f"\n{TASK_NAMES_LINE}")
    return 0


# what `--task` takes besides these names (envs.resolver.ROBOSUITE_TASKS)
TASK_NAMES_LINE = ("--task robosuite runs every robosuite task, the first table ('all' is its older name); a LIBERO suite's name "
                   "runs its tasks")

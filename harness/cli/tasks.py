"""`octo-harness tasks`: the registered robosuite and LIBERO tasks and their instructions."""

from __future__ import annotations


def add_parser(sub) -> None:
    sub.add_parser("tasks", help="list the registered tasks").set_defaults(func=main)


def main(args) -> int:
    import envs

    print(envs.task_table(libero=True))
    return 0

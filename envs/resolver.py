"""The one task resolver: task names (robosuite tasks, LIBERO suites and tasks, any registered suite's) -> tasks.

`get_task("Lift")`, `get_task("lift")`, `get_task("libero_object/3")` -> TaskSpec; `resolve_names(["lift",
"libero_object"])` -> canonical names, a name that stands for several tasks expanded to them (a LIBERO suite;
"robosuite", or its older name "all" = every robosuite task). An unknown name raises `UnknownTaskError` (one line
naming the closest task). Each suite (envs.suites) says which names are its own.
"""

from __future__ import annotations

from envs import suites
from envs.robosuite_suite import ROBOSUITE_TASKS  # noqa: F401 - the names that stand for every robosuite task
from envs.taskspec import TaskSpec


def get_task(name: str) -> TaskSpec:
    """The task called `name` (a robosuite task, a LIBERO task "libero_object/3", a registered suite's); an unknown
    name raises `UnknownTaskError` listing the known ones and the closest."""
    return suites.get_task(name)


def resolve_names(names: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """Task names (a suite's group name = its tasks: "robosuite" or "all", a LIBERO suite; "libero_object/3" = one)
    -> registry names, case-insensitive, deduplicated, in the order given."""
    resolved: list[str] = []
    for name in names:
        canonicals = next((found for suite in suites.suites() if (found := suite.expand(name)) is not None), None)
        if canonicals is None:
            canonicals = [suites.get_task(name).name]  # raises the registry's error naming the closest task
        resolved += [c for c in canonicals if c not in resolved]
    return tuple(resolved)

"""The one task resolver: task names (robosuite tasks, LIBERO suites and tasks) -> registered tasks.

`get_task("Lift")`, `get_task("lift")`, `get_task("libero_object/3")` -> TaskSpec; `resolve_names(["lift",
"libero_object"])` -> canonical names, a LIBERO suite expanded to its tasks, "robosuite" (or its older name "all") =
every robosuite task. An unknown
name raises `UnknownTaskError` (one line naming the closest task). Reads `envs.tasks` and `envs.libero_tasks`, which
import neither this module nor each other.
"""

from __future__ import annotations

import difflib

from envs import libero_tasks
from envs.taskspec import TaskSpec, UnknownTaskError
from envs.tasks import list_tasks

# the names that stand for every robosuite task, as a suite's name stands for its tasks: "robosuite", and "all", its
# older name, kept for existing commands (it never ran LIBERO's suites, which are named one by one)
ROBOSUITE_TASKS = ("robosuite", "all")


def get_task(name: str) -> TaskSpec:
    """The task called `name` (a robosuite task, or a LIBERO task "libero_object/3"); an unknown name raises
    `UnknownTaskError` listing the known ones and the closest."""
    by_name = {task.name: task for task in list_tasks()}
    if name in by_name:
        return by_name[name]
    if libero_tasks.is_libero(name):
        if "/" not in name:
            raise UnknownTaskError(f"{name!r} is a LIBERO suite, not one task; name a task ({name}/0) or pass the suite "
                                   "to --task, which runs all its tasks")
        return libero_tasks.get_libero_task(name)
    lowered = {task.lower(): task for task in by_name}
    if name.lower() in lowered:
        return by_name[lowered[name.lower()]]
    close = difflib.get_close_matches(name.lower(), list(lowered), n=1, cutoff=0.4)
    hint = f"did you mean {lowered[close[0]]!r}? " if close else ""
    raise UnknownTaskError(f"unknown task {name!r}; {hint}known tasks: {', '.join(by_name)} (`robosuite`: all of "
                           "them); LIBERO suites: "
                           "libero_spatial, libero_object, libero_goal, libero_10, libero_90 (see `octo-harness tasks`)")


def resolve_names(names: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """Task names ("robosuite" or "all" = every robosuite task; a LIBERO suite name = its tasks, "libero_object/3" =
    one) -> registry names, case-insensitive, deduplicated, in the order given."""
    registry = {spec.name.lower(): spec.name for spec in list_tasks()}
    resolved: list[str] = []
    for name in names:
        if name.lower() in ROBOSUITE_TASKS:
            canonicals = list(registry.values())
        elif libero_tasks.is_libero(name):  # "libero_object" (the whole suite) or "libero_object/3"
            canonicals = libero_tasks.expand(name)
        else:
            canonical = registry.get(name.lower())
            if canonical is None:
                get_task(name)  # raises the registry's error naming the closest task
            canonicals = [canonical]
        resolved += [c for c in canonicals if c not in resolved]
    return tuple(resolved)

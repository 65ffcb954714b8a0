"""The suite registry: the `Suite` contract, the registered suites in order, and the suite of a task name.

An environment suite (robosuite's tasks, LIBERO's, a toy one in a package of its own) is one `Suite` subclass and one
registry entry. It declares:
  name            the family key: `TaskSpec.simulator` of its tasks, a manifest's `conventions` ("default:<name>") and
                  a protocol's `family_env`, the key its platform side is recorded under
  title           how the help and the docs name it ("LIBERO")
  defaults        its conventions' defaults ({"image_convention", "action_space"}) for a key neither the command line
                  nor the checkpoint's harness.toml sets; its default cameras are `default_cameras(task)`
  default_note    why those are the defaults, in the console line a run that uses them prints ("published protocol")
  runs            "in-process" (the env steps in the process that made it) or "server" (behind a server process of
                  its own, as LIBERO's: a lost server is an infrastructure failure, `lost`)
  platform_numerics  the keys of its `platform()` block that enter the platform fingerprint (none: nothing recorded)
and implements what the harness asks of a suite, by task name, never by the suite's name:
  tasks()         its TaskSpecs, in listing order
  task(name)      the TaskSpec `name` names (exact or case-insensitive), None when the name is not this suite's; a
                  name that is this suite's but no task of it raises UnknownTaskError (one line)
  expand(name)    the task names a name given to --task stands for (a task, or a group: "robosuite", a LIBERO
                  suite), None when it is not this suite's
  make(task, config)  the env (a gymnasium env: observations image_<key> and proprio, `info` with success,
                  instruction, task, step, action_clipped and, with config.masks, masks) for an `envs.wrappers.EnvConfig`
  default_cameras(task)  the CameraSpecs of a run that names none
  check(tasks, first_seed, last_seed)  before anything loads: a ValueError (one line naming the fix) when the run
                  cannot go (LIBERO: its environment is not set up, or a seed names no stored initial state)
  platform()      its side of the platform record (None: nothing beyond the harness's own)
  lost(exc)       what an episode's exception lost ("LIBERO server"): retried as an infrastructure failure; None else
  errors()        exception classes the command line prints as one line (exit 2), not as a bug
  table()         its part of `octo-harness tasks`; known(): its part of an unknown task's error; label(tasks): how
                  the console line of its default conventions names its tasks

Where suites come from, in this order (the order `octo-harness tasks` lists them and task names are looked up in):
  1. the built-in suites, named here as "module:Class" (`BUILTINS`) and imported on first use, so this module imports
     none of them and they import it (one direction); their modules import their simulators only inside `make`;
  2. the entry points of the group `octo_harness.suites` of every installed distribution, by name: a suite shipped in
     a package of its own is found by every process that imports the harness, spawned `--workers` and Ray workers
     included;
  3. `register(cls)` / `registered(cls)` at run time: known to this process only.
This module imports nothing of envs/ but `envs.taskspec` and `envs.plugins` (the registry it shares with the probes), so `envs.options` can word the built-in suites' defaults.
"""

from __future__ import annotations

import difflib
from typing import Any, ClassVar, Mapping, Sequence

from envs.plugins import PluginRegistry
from envs.taskspec import TaskSpec, UnknownTaskError

BUILTINS = ("envs.robosuite_suite:RobosuiteSuite", "envs.libero_suite:LiberoSuite")
ENTRY_POINTS = "octo_harness.suites"  # the entry-point group a distribution registers its suites under
RUNS = ("in-process", "server")


class SuiteLoadError(ImportError):
    """A suite named by the built-ins or an entry point cannot be loaded (one line naming it)."""


class Suite:
    """One environment suite (see the module docstring). Subclasses set the class attributes and implement `tasks`
    and `make`; the registry holds one instance per class."""

    name: ClassVar[str] = ""
    title: ClassVar[str] = ""
    defaults: ClassVar[Mapping[str, str]] = {"image_convention": "upright", "action_space": "octo-delta"}
    default_note: ClassVar[str] = "the suite's default"
    runs: ClassVar[str] = "in-process"
    platform_numerics: ClassVar[tuple[str, ...]] = ()

    def tasks(self) -> Sequence[TaskSpec]:
        raise NotImplementedError

    def make(self, task: TaskSpec, config) -> Any:
        raise NotImplementedError

    def default_cameras(self, task: TaskSpec) -> tuple:
        """image_primary = the task's primary camera at 256 px, image_wrist = robot0_eye_in_hand at 128 px."""
        from envs.render import CameraSpec

        return (CameraSpec("image_primary", task.primary_camera, 256),
                CameraSpec("image_wrist", "robot0_eye_in_hand", 128))

    def task(self, name: str) -> TaskSpec | None:
        by_name = {spec.name: spec for spec in self.tasks()}
        if name in by_name:
            return by_name[name]
        lowered = {key.lower(): spec for key, spec in by_name.items()}
        return lowered.get(name.lower())

    def expand(self, name: str) -> list[str] | None:
        spec = self.task(name)
        return None if spec is None else [spec.name]

    def hint_names(self) -> Sequence[str]:
        """The names an unknown task's error may suggest as the closest."""
        return [spec.name for spec in self.tasks()]

    def known(self) -> str:
        return f"{self.title or self.name} tasks: {', '.join(spec.name for spec in self.tasks())}"

    def label(self, tasks: Sequence[str]) -> str:
        return ", ".join(tasks)

    def table(self) -> str:
        return task_table(self.tasks())

    def check(self, tasks: Sequence[TaskSpec], first_seed: int, last_seed: int) -> None:
        """Nothing to check by default."""

    def platform(self) -> dict | None:
        return None

    def lost(self, exc: BaseException) -> str | None:
        return None

    def errors(self) -> tuple[type[BaseException], ...]:
        return ()


def task_table(tasks: Sequence[TaskSpec]) -> str:
    """A plain-text table of tasks: name, max steps, targets, instruction."""
    rows = [("task", "max steps", "targets", "instruction")]
    rows += [(t.name, str(t.max_episode_steps), ", ".join(t.targets), t.instruction) for t in tasks]
    widths = [max(len(row[i]) for row in rows) for i in range(3)]
    return "\n".join(f"{r[0]:{widths[0]}}  {r[1]:>{widths[1]}}  {r[2]:{widths[2]}}  {r[3]}" for r in rows)


def _check(cls: type[Suite]) -> None:
    if cls.runs not in RUNS:
        raise ValueError(f"suite {cls.name!r}: runs must be one of {', '.join(RUNS)}, got {cls.runs!r}")


_SUITES = PluginRegistry("suite", Suite, BUILTINS, ENTRY_POINTS, SuiteLoadError, make=lambda cls: cls(), check=_check)
builtin = _SUITES.builtin  # the built-in suite classes, imported (what the help and the docs word the defaults of)
register = _SUITES.register  # add a suite class (usable as a decorator); a taken or empty name is a ValueError
unregister = _SUITES.unregister
registered = _SUITES.registered  # the suite registered for the duration of a block (one defined in a test)


def suites() -> tuple[Suite, ...]:
    """Every registered suite (an instance of each), in registration order."""
    return _SUITES.values()


def get(name: str) -> Suite:
    """The suite called `name` (a family key, e.g. a TaskSpec's simulator)."""
    return _SUITES.get(name)


def get_task(name: str) -> TaskSpec:
    """The task called `name` in any suite; an unknown name raises `UnknownTaskError` listing the known ones and the
    closest."""
    for suite in suites():
        spec = suite.task(name)
        if spec is not None:
            return spec
    lowered = {n.lower(): n for suite in suites() for n in suite.hint_names()}
    close = difflib.get_close_matches(name.lower(), list(lowered), n=1, cutoff=0.4)
    hint = f"did you mean {lowered[close[0]]!r}? " if close else ""
    known = "; ".join(suite.known() for suite in suites())
    raise UnknownTaskError(f"unknown task {name!r}; {hint}{known} (see `octo-harness tasks`)")


def of(name: str) -> Suite:
    """The suite of a task or of a name that stands for several ("libero_object", "robosuite")."""
    for suite in suites():
        if _expands(suite, name):
            return suite
    return get(get_task(name).simulator)  # raises UnknownTaskError


def _expands(suite: Suite, name: str) -> bool:
    try:
        return suite.expand(name) is not None
    except UnknownTaskError:  # the suite's name, but out of range: still its
        return True


def of_tasks(tasks: Sequence[str]) -> dict[Suite, list[TaskSpec]]:
    """{suite: its TaskSpecs among `tasks`}, suites in registration order."""
    specs = [get_task(t) for t in tasks]
    return {suite: [s for s in specs if s.simulator == suite.name] for suite in suites()
            if any(s.simulator == suite.name for s in specs)}


def lost(exc: BaseException) -> str | None:
    """What `exc` lost, where a registered suite says it was lost (infrastructure, retried); None otherwise."""
    for suite in suites():
        what = suite.lost(exc)
        if what:
            return what
    return None


def errors() -> tuple[type[BaseException], ...]:
    """Every registered suite's one-line error classes."""
    return tuple(dict.fromkeys(cls for suite in suites() for cls in suite.errors()))

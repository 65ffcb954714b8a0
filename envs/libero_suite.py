"""The LIBERO suite: LIBERO's five suites of tasks (envs.libero_tasks), each env behind a server in LIBERO's own
Python environment (envs.libero_env, docs/libero.md)."""

from __future__ import annotations

import sys

from envs import libero_tasks
from envs.suites import Suite
from envs.taskspec import TaskSpec, UnknownTaskError


class LiberoSuite(Suite):
    name = "libero"
    title = "LIBERO"
    # the published evaluation's (OpenVLA's run_libero_eval.py): the rendered frame turned 180 degrees, LIBERO's action
    # convention; the stored initial states and settle steps are the LIBERO env's own
    defaults = {"image_convention": "rot180", "action_space": "libero"}
    default_note = "published protocol"
    runs = "server"
    # the LIBERO side's keys (`platform()`, recorded under "libero") that enter the platform fingerprint
    platform_numerics = ("libero_package", "robosuite", "mujoco", "numpy", "gl.backend", "gl.vendor", "gl.renderer",
                         "gl.version")

    def tasks(self) -> tuple[TaskSpec, ...]:
        return libero_tasks.libero_tasks()

    def task(self, name: str) -> TaskSpec | None:
        if not libero_tasks.is_libero(name):
            return None
        if "/" not in name:
            raise UnknownTaskError(f"{name!r} is a LIBERO suite, not one task; name a task ({name}/0) or pass the suite "
                                   "to --task, which runs all its tasks")
        return libero_tasks.get_libero_task(name)

    def expand(self, name: str) -> list[str] | None:
        """"libero_object" (the whole suite) or "libero_object/3" -> its task names; None for another suite's name."""
        return libero_tasks.expand(name) if libero_tasks.is_libero(name) else None

    def hint_names(self) -> tuple[str, ...]:
        return ()

    def known(self) -> str:
        return "LIBERO suites: " + ", ".join(libero_tasks.SUITES)

    def label(self, tasks) -> str:
        return ", ".join(dict.fromkeys(t.split("/")[0] for t in tasks))  # the suites, not each task

    def table(self) -> str:
        return ("LIBERO (its own simulator stack; set up with `bash scripts/setup_libero.sh`)\n"
                + libero_tasks.suite_table())

    def make(self, task: TaskSpec, config):
        from envs.libero_env import LiberoEnv

        return LiberoEnv(task, config)

    def check(self, tasks, first_seed: int, last_seed: int) -> None:
        """Every episode seed must name a stored initial state (episode k of a task starts from state seed + k), and
        LIBERO's environment must be set up (one line naming the set-up command)."""
        for spec in tasks:
            if last_seed >= spec.initial_states:
                raise ValueError(f"{spec.name} stores {spec.initial_states} initial states (0..{spec.initial_states - 1}) "
                                 f"and episode k starts from state --seed + k: --seed {first_seed} --episodes "
                                 f"{last_seed - first_seed + 1} would need state {last_seed}; use --seed + --episodes <= "
                                 f"{spec.initial_states}")
        from envs.libero_env import libero_python

        libero_python()  # LiberoEnvironmentMissing: "LIBERO's environment is not set up ...; run: bash scripts/setup_libero.sh"

    def platform(self) -> dict:
        """Its package, robosuite, MuJoCo, numpy and Python versions and its GL renderer, as its own environment reports
        them (a server started for the purpose); {"error": ...} when none starts (the env itself reports the fault)."""
        from envs.libero_env import libero_versions

        try:
            return libero_versions()
        except Exception as exc:  # noqa: BLE001 - provenance must never stop a run
            return {"error": f"{type(exc).__name__}: {exc}".splitlines()[0]}

    def lost(self, exc: BaseException) -> str | None:
        """A LIBERO server that died or stopped answering (envs.libero_env.LiberoServerLost)."""
        module = sys.modules.get("envs.libero_env")  # loaded wherever a LIBERO env ran
        return "LIBERO server" if module is not None and isinstance(exc, module.LiberoServerLost) else None

    def errors(self) -> tuple[type[BaseException], ...]:
        from envs.libero_env import LiberoServerError

        return (LiberoServerError,)

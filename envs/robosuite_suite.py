"""The robosuite suite: robosuite 1.5's single-arm tasks (envs.tasks), stepped in this process (envs.robosuite_env)."""

from __future__ import annotations

from envs.suites import Suite
from envs.taskspec import TaskSpec

# the names that stand for every robosuite task, as a suite's name stands for its tasks: "robosuite", and "all", its
# older name, kept for existing commands (it never ran LIBERO's suites, which are named one by one)
ROBOSUITE_TASKS = ("robosuite", "all")


class RobosuiteSuite(Suite):
    name = "robosuite"
    title = "robosuite"
    defaults = {"image_convention": "upright", "action_space": "octo-delta"}
    default_note = "the harness's robosuite default"
    runs = "in-process"

    def tasks(self) -> tuple[TaskSpec, ...]:
        from envs.tasks import list_tasks

        return tuple(list_tasks())

    def expand(self, name: str) -> list[str] | None:
        if name.lower() in ROBOSUITE_TASKS:
            return [spec.name for spec in self.tasks()]
        return super().expand(name)

    def make(self, task: TaskSpec, config):
        from envs.robosuite_env import RobosuiteEnv

        return RobosuiteEnv(task, config)

    def default_cameras(self, task: TaskSpec) -> tuple:
        from envs.robosuite_env import default_cameras

        return default_cameras(task)

    def known(self) -> str:
        return f"known tasks: {', '.join(spec.name for spec in self.tasks())} (`robosuite`: all of them)"

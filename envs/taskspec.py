"""What a task is: `TaskSpec` (one registered task: instruction, targets, episode length, simulator) and
`UnknownTaskError`.

Both task registries build on it: `envs.tasks` (the robosuite tasks) and `envs.libero_tasks` (LIBERO's suites);
`envs.resolver` turns names into tasks over both. It imports nothing of the package, so no registry imports another.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TaskSpec:
    name: str  # registry name, also the gymnasium id "octo_harness/<name>-v0"
    robosuite_env: str  # robosuite environment class name
    instruction: str  # default language instruction
    paraphrases: tuple[str, ...]  # alternative phrasings of the same instruction
    targets: tuple[str, ...]  # body-name prefixes of the target object(s)
    max_episode_steps: int  # truncation limit at 20 Hz control
    primary_camera: str = "agentview"  # robosuite camera behind the default image_primary
    robosuite_options: tuple[tuple[str, object], ...] = ()  # fixed extra kwargs for robosuite.make
    simulator: str = "robosuite"  # the suite that runs it (envs.suites): "robosuite", "libero", a registered suite's name
    initial_states: int = 0  # LIBERO: stored initial states (episode seed s starts from state s)
    goal: tuple[str, ...] = ()  # body-name prefixes of the goal region (where the target goes), for the goal mask

    @property
    def gym_id(self) -> str:
        return f"octo_harness/{self.name}-v0"


class UnknownTaskError(ValueError):
    """A task name that is not in the registry."""

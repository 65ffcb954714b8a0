"""Headless robosuite tasks as gymnasium environments for evaluating Octo (public entry points).

Importing this package first chooses the headless GL backend (`envs.gl.configure`: EGL, else OSMesa)
because MuJoCo reads it at import time, then registers every task with gymnasium as
"octo_harness/<Task>-v0". robosuite itself is imported lazily by `make`.

    import envs
    env = envs.make("Lift", masks=True)
    obs, info = env.reset(seed=0)
"""

from __future__ import annotations

from envs import gl

gl.configure()

import functools  # noqa: E402

import gymnasium  # noqa: E402

from envs.actions import ActionAdapterConfig, ActionAdapterError, adapt_action  # noqa: E402
from envs.gl import HeadlessGLError  # noqa: E402
from envs.render import UnknownCameraError  # noqa: E402
from envs.robosuite_env import EnvConfig, EnvConfigError, RobosuiteEnv, WrongThreadError, parse_cameras  # noqa: E402
from envs.tasks import TaskSpec, UnknownTaskError, get_task, list_tasks, task_table  # noqa: E402

__all__ = [
    "ActionAdapterConfig",
    "ActionAdapterError",
    "EnvConfig",
    "EnvConfigError",
    "HeadlessGLError",
    "RobosuiteEnv",
    "TaskSpec",
    "UnknownCameraError",
    "UnknownTaskError",
    "WrongThreadError",
    "adapt_action",
    "get_task",
    "list_tasks",
    "make",
    "make_vector",
    "task_table",
]


def make(
    task: str,
    *,
    cameras: dict[str, tuple[str, int]] | None = None,
    masks: bool = False,
    terminate_on_success: bool = True,
    max_episode_steps: int | None = None,
    instruction: str | None = None,
    action_adapter: ActionAdapterConfig | None = None,
    fast_render: bool = False,
    model_seed: int = 0,
    render_mode: str | None = None,
    **robosuite_options,
) -> RobosuiteEnv:
    """A gymnasium environment for registered task `task` (see `list_tasks()`).

    cameras: {observation key: (robosuite camera, square size)}; None gives image_primary = agentview
    (Door: sideview) 256 px and image_wrist = robot0_eye_in_hand 128 px; {} renders nothing (no GL needed).
    Remaining keyword arguments go to `robosuite.make` unchanged.
    """
    spec = get_task(task)
    if max_episode_steps is not None and max_episode_steps <= 0:
        raise EnvConfigError(f"max_episode_steps must be positive, got {max_episode_steps}")
    config = EnvConfig(
        cameras=parse_cameras(cameras, spec),
        masks=masks,
        terminate_on_success=terminate_on_success,
        max_episode_steps=max_episode_steps,
        instruction=instruction,
        action_adapter=action_adapter,
        fast_render=fast_render,
        model_seed=model_seed,
        render_mode=render_mode,
        robosuite_options=tuple(sorted(robosuite_options.items())),
    )
    return RobosuiteEnv(spec, config)


def make_vector(task: str, num_envs: int, **options) -> gymnasium.vector.AsyncVectorEnv:
    """`num_envs` copies of `make(task, **options)`, each in its own process started with spawn (never fork)."""
    if num_envs <= 0:
        raise EnvConfigError(f"num_envs must be positive, got {num_envs}")
    get_task(task)  # fail here, not in the workers, on an unknown name
    factory = functools.partial(make, task, **options)
    return gymnasium.vector.AsyncVectorEnv([factory] * num_envs, context="spawn")


def _register_all() -> None:
    """Register every task as "octo_harness/<name>-v0" (idempotent)."""
    for spec in list_tasks():
        if spec.gym_id not in gymnasium.registry:
            gymnasium.register(spec.gym_id, entry_point=functools.partial(make, spec.name))


_register_all()

"""Headless robosuite tasks as gymnasium environments for evaluating Octo (public entry points).

Importing this package first chooses the headless GL backend (`envs.gl.configure`: EGL, else OSMesa)
because MuJoCo reads it at import time, then registers every task with gymnasium as
"octo_harness/<Task>-v0". robosuite itself is imported lazily by `make`; its import-time warnings about
files and robots the harness does not use are dropped (`robosuite_env.quiet_robosuite_import`).

    import envs
    env = envs.make("Lift", masks=True)
    env = envs.make("Lift", envs.EnvOptions(cameras=(("image_primary", "agentview", 84),), action_space="robosuite"))
    obs, info = env.reset(seed=0)

`EnvOptions` (envs.options) is the serialisable part a run protocol records; keyword arguments of
`make` with the same names override it.
"""

from __future__ import annotations

from envs import gl

gl.configure()

import functools  # noqa: E402

import gymnasium  # noqa: E402

from envs.actions import ActionAdapterConfig, ActionAdapterError, adapt_action  # noqa: E402
from envs.gl import HeadlessGLError  # noqa: E402
from envs.options import ACTION_SPACES, IMAGE_CONVENTIONS, EnvOptions, parse_camera, to_convention  # noqa: E402
from envs.perturbations import Perturbation, PerturbationError, parse_perturb  # noqa: E402
from envs.render import UnknownCameraError  # noqa: E402
from envs.robosuite_env import EnvConfigError, RobosuiteEnv, WrongThreadError, quiet_robosuite_import  # noqa: E402
from envs.wrappers import EnvConfig, parse_cameras  # noqa: E402

quiet_robosuite_import()
from envs import suites  # noqa: E402
from envs.resolver import get_task  # noqa: E402
from envs.suites import Suite  # noqa: E402
from envs.tasks import list_tasks, task_table  # noqa: E402
from envs.taskspec import TaskSpec, UnknownTaskError  # noqa: E402

__all__ = [
    "ACTION_SPACES",
    "IMAGE_CONVENTIONS",
    "ActionAdapterConfig",
    "ActionAdapterError",
    "EnvConfig",
    "EnvConfigError",
    "EnvOptions",
    "HeadlessGLError",
    "Perturbation",
    "PerturbationError",
    "RobosuiteEnv",
    "Suite",
    "TaskSpec",
    "UnknownCameraError",
    "UnknownTaskError",
    "WrongThreadError",
    "adapt_action",
    "get_task",
    "list_tasks",
    "make",
    "make_vector",
    "parse_camera",
    "parse_perturb",
    "suites",
    "to_convention",
    "task_table",
]


def make(
    task: str,
    options: EnvOptions | None = None,
    *,
    cameras: dict[str, tuple[str, int]] | None = None,
    masks: bool | None = None,
    fast_render: bool | None = None,
    image_convention: str | None = None,
    action_space: str | None = None,
    terminate_on_success: bool = True,
    max_episode_steps: int | None = None,
    instruction: str | None = None,
    action_adapter: ActionAdapterConfig | None = None,
    model_seed: int = 0,
    render_mode: str | None = None,
    perturb=None,
    **robosuite_options,
) -> gymnasium.Env:
    """A gymnasium environment for registered task `task`, made by its suite (envs.suites: robosuite's tasks in this
    process, LIBERO's such as "libero_object/3" in LIBERO's own environment through `envs.libero_env.LiberoEnv`, a
    registered suite's by its `make`).

    options: masks, fast_render, cameras, image_convention, action_space (see envs.options); the keyword
    arguments of the same names override it when given. cameras: {observation key: (robosuite camera,
    square size)}; None gives image_primary = agentview (Door: sideview) 256 px and image_wrist =
    robot0_eye_in_hand 128 px; {} renders nothing (no GL needed).
    perturb: "KIND[@KEY]:LEVEL[,...]" or parsed perturbations (envs.perturbations); None or level 0 = nominal.
    Remaining keyword arguments go to `robosuite.make` unchanged.
    """
    spec = get_task(task)
    options = (options or EnvOptions()).replace(cameras=cameras, masks=masks, fast_render=fast_render,
                                                image_convention=image_convention, action_space=action_space)
    if max_episode_steps is not None and max_episode_steps <= 0:
        raise EnvConfigError(f"max_episode_steps must be positive, got {max_episode_steps}")
    config = EnvConfig(
        cameras=parse_cameras(options.camera_dict, spec),
        masks=options.masks,
        terminate_on_success=terminate_on_success,
        max_episode_steps=max_episode_steps,
        instruction=instruction,
        action_adapter=action_adapter,
        fast_render=options.fast_render,
        image_convention=options.image_convention,
        action_space=options.action_space,
        hold_gripper=options.hold_gripper,
        model_seed=model_seed,
        render_mode=render_mode,
        robosuite_options=tuple(sorted(robosuite_options.items())),
        perturbations=perturb if isinstance(perturb, tuple) else parse_perturb(perturb),
    )
    return suites.get(spec.simulator).make(spec, config)


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

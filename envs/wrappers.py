"""What every suite's env shares between its simulator and the policy: the config it is made with (`EnvConfig`), the
action space the policy acts in over the simulator's controller input (`ControllerActions`: octo-delta, robosuite,
libero, and the held gripper of a 6-D model) and the image convention of everything pixel-indexed it returns
(`ImageConvention`: frames, masks; `render()` upright again).

An env (envs.robosuite_env.RobosuiteEnv, envs.libero_env.LiberoEnv, a suite's own) renders upright frames and steps
its controller with what these wrappers hand it:

    actions = ControllerActions(config.action_space, adapter, config.hold_gripper)   # its action_space: actions.space
    view = ImageConvention(config.image_convention)
    osc = actions(action)               # the controller input; actions.clipped counts the clipped steps (reset())
    obs = view.frames(upright_frames)   # masks: view.masks({name: upright mask}); render(): view.upright(frame)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np

from envs.actions import ActionAdapterConfig, controller_action
from envs.options import ACTION_SPACES, IMAGE_CONVENTIONS, EnvConfigError, to_convention
from envs.render import CameraSpec
from envs.taskspec import TaskSpec


@dataclass(frozen=True)
class EnvConfig:
    cameras: tuple[CameraSpec, ...] = ()  # no cameras: no rendering; `make` fills in the task's defaults
    masks: bool = False
    terminate_on_success: bool = True
    max_episode_steps: int | None = None  # None: the task's default
    instruction: str | None = None  # None: the task's default instruction
    action_adapter: ActionAdapterConfig | None = None  # None: scales read from the controller's output limits
    fast_render: bool = False  # no shadows, reflections or skybox
    model_seed: int = 0  # seeds randomised model properties at construction (object sizes, table height)
    render_mode: str | None = None  # None or "rgb_array" (returns the first camera's latest frame)
    robosuite_options: tuple[tuple[str, object], ...] = field(default_factory=tuple)  # extra robosuite.make kwargs
    image_convention: str = "upright"  # "upright" | "opengl" | "rot180" (see envs.options)
    action_space: str = "octo-delta"  # "octo-delta" | "robosuite" | "libero" (see envs.options)
    hold_gripper: float | None = None  # 6-D actions (arm only), this gripper value appended (see envs.options)
    perturbations: tuple = ()  # envs.perturbations.Perturbation values (level > 0); () = the nominal scene


def parse_cameras(cameras: dict[str, tuple[str, int]] | None, task: TaskSpec) -> tuple[CameraSpec, ...]:
    """{obs key: (camera, size)} -> camera specs; None gives the task's suite's defaults (envs.suites)."""
    if cameras is None:
        from envs import suites

        return tuple(suites.get(task.simulator).default_cameras(task))
    specs = []
    for key, value in cameras.items():
        if not (isinstance(value, (tuple, list)) and len(value) == 2 and isinstance(value[1], (int, np.integer)) and value[1] > 0):
            raise EnvConfigError(f"camera {key!r}: expected (robosuite camera name, positive size), got {value!r}")
        if key == "proprio":
            raise EnvConfigError("camera key 'proprio' is reserved for the proprioceptive state; choose another key")
        specs.append(CameraSpec(key, str(value[0]), int(value[1])))
    return tuple(specs)


def check_config(config: EnvConfig) -> None:
    """EnvConfigError (one line) for options that cannot go together or are unknown, before a simulator loads."""
    if config.masks and not config.cameras:
        raise EnvConfigError("masks=True needs at least one camera")
    if config.render_mode not in (None, "rgb_array"):
        raise EnvConfigError(f"render_mode {config.render_mode!r} unsupported; use None or 'rgb_array'")
    if config.render_mode == "rgb_array" and not config.cameras:
        raise EnvConfigError("render_mode='rgb_array' needs at least one camera")
    if config.image_convention not in IMAGE_CONVENTIONS:
        raise EnvConfigError(f"image convention {config.image_convention!r} unknown; use one of {', '.join(IMAGE_CONVENTIONS)}")
    if config.action_space not in ACTION_SPACES:
        raise EnvConfigError(f"action space {config.action_space!r} unknown; use one of {', '.join(ACTION_SPACES)}")


def action_box(action_space: str, adapter: ActionAdapterConfig, hold_gripper: float | None = None) -> gym.spaces.Box:
    """The policy's action space of `action_space` (7-D; 6-D with `hold_gripper`)."""
    if action_space == "robosuite":  # the controller's own input range
        space = gym.spaces.Box(-1.0, 1.0, (7,), dtype=np.float32)
    elif action_space == "libero":  # OSC input, gripper 1 open / 0 closed (envs.actions.libero_action)
        space = gym.spaces.Box(np.array([-1.0] * 6 + [0.0], np.float32), np.ones(7, np.float32))
    else:  # the range the adapter passes unclipped: +-position_max metres, about +-rotation_max radians, gripper [0, 1]
        high = np.array([adapter.position_max] * 3 + [adapter.rotation_max] * 3 + [1.0], dtype=np.float32)
        low = np.concatenate([-high[:6], [0.0]]).astype(np.float32)
        space = gym.spaces.Box(low, high, dtype=np.float32)
    if hold_gripper is not None:  # arm-only actions; the gripper is held at the given value
        space = gym.spaces.Box(space.low[:6], space.high[:6], dtype=np.float32)
    return space


class ControllerActions:
    """The policy's actions in `action_space` over a 7-D OSC_POSE-style controller input (6 arm values in [-1, 1],
    gripper -1 open / +1 closed): `space` (the env's action_space), `actions(action)` -> the controller input, and
    `clipped`, the steps clipped since `reset()` (info["action_clipped"])."""

    def __init__(self, action_space: str, adapter: ActionAdapterConfig, hold_gripper: float | None = None):
        self.action_space, self.adapter, self.hold_gripper = action_space, adapter, hold_gripper
        self.space = action_box(action_space, adapter, hold_gripper)
        self.clipped = 0

    def reset(self) -> None:
        self.clipped = 0

    def __call__(self, action) -> np.ndarray:
        osc, clipped = controller_action(action, self.action_space, self.adapter, self.hold_gripper)
        self.clipped += int(clipped)
        return osc


class ImageConvention:
    """Upright pixels -> the env's image convention ("upright", "opengl", "rot180": envs.options.to_convention, its
    own inverse), for frames, masks and the upright `render()` frame."""

    def __init__(self, convention: str):
        if convention not in IMAGE_CONVENTIONS:
            raise EnvConfigError(f"image convention {convention!r} unknown; use one of {', '.join(IMAGE_CONVENTIONS)}")
        self.name = convention

    def __call__(self, upright: np.ndarray) -> np.ndarray:
        return to_convention(upright, self.name)

    def frames(self, upright: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {key: to_convention(frame, self.name) for key, frame in upright.items()}

    def masks(self, named: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {name: to_convention(mask, self.name) for name, mask in named.items()}

    def upright(self, frame: np.ndarray) -> np.ndarray:
        """A frame in this convention -> upright (a copy: render() is for people)."""
        return to_convention(frame, self.name).copy()

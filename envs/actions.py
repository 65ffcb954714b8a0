"""Action spaces as pure numpy: Octo's 7-D end-effector delta, or robosuite's own OSC_POSE (delta) input.

`adapt_action` maps Octo's delta to the controller input; `passthrough_action` takes the controller
input as it is (action space "robosuite": what robosuite and robomimic datasets store).

Octo (Bridge convention): `(dx, dy, dz, droll, dpitch, dyaw, gripper)`: translation in metres, rotation
delta in radians as Euler angles (`rotation_convention`, scipy sequence, default extrinsic "xyz"),
gripper in [0, 1] with 1 = open. robosuite's OSC_POSE input is `(6 arm values in [-1, 1], 1 gripper value)`
where the controller multiplies the arm values by its `output_max` (robosuite 1.5 default: 0.05 m and
0.5 rad) and reads the rotation as an axis-angle vector applied in the robot base frame
(goal = R_delta @ R_current). The gripper value is -1 fully open, +1 fully closed.

Mapping:
- position: `dx / position_max`, each component clipped to [-1, 1] (what robosuite itself would do);
- rotation: Euler -> rotation vector, divided by `rotation_max`; when a component exceeds 1 the whole
  vector is scaled down so the rotation axis is kept;
- gripper: openness `o` (= g, or 1 - g when `gripper_open_value` is 0) -> `1 - 2 o` ("continuous",
  clipped to [-1, 1]) or -1 / +1 around `gripper_threshold` ("binary").
Any clipping of any component makes `clipped` true; the environment counts such steps per episode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

_ROTATION_CONVENTIONS = ("xyz", "XYZ", "zyx", "ZYX", "rotvec")


class ActionAdapterError(ValueError):
    """An invalid adapter configuration or action."""


@dataclass(frozen=True)
class ActionAdapterConfig:
    position_max: float = 0.05  # metres that map to OSC input 1.0 (the controller's output_max for x, y, z)
    rotation_max: float = 0.5  # radians that map to OSC input 1.0 (the controller's output_max for rotation)
    rotation_convention: str = "xyz"  # scipy Euler sequence of the rotation delta ("xyz" = extrinsic), or "rotvec"
    gripper_mode: str = "continuous"  # "continuous": 1 - 2*openness; "binary": open/close at gripper_threshold
    gripper_threshold: float = 0.5  # openness at or above which "binary" opens
    gripper_open_value: float = 1.0  # the action value meaning fully open: 1.0 (Octo) or 0.0

    def __post_init__(self) -> None:
        if not (self.position_max > 0 and self.rotation_max > 0):
            raise ActionAdapterError("position_max and rotation_max must be positive (controller output limits)")
        if self.rotation_convention not in _ROTATION_CONVENTIONS:
            raise ActionAdapterError(
                f"rotation_convention {self.rotation_convention!r} unknown; use one of {', '.join(_ROTATION_CONVENTIONS)}"
            )
        if self.gripper_mode not in ("continuous", "binary"):
            raise ActionAdapterError(f"gripper_mode {self.gripper_mode!r} unknown; use 'continuous' or 'binary'")
        if self.gripper_open_value not in (0.0, 1.0):
            raise ActionAdapterError("gripper_open_value must be 1.0 (1 = open) or 0.0 (0 = open)")


def rotation_delta_to_rotvec(rotation: np.ndarray, convention: str) -> np.ndarray:
    """(3,) rotation delta in `convention` -> (3,) rotation vector (axis * angle, radians)."""
    if convention == "rotvec":
        return np.asarray(rotation, dtype=np.float64)
    return Rotation.from_euler(convention, rotation).as_rotvec()


def adapt_action(action: np.ndarray, config: ActionAdapterConfig = ActionAdapterConfig()) -> tuple[np.ndarray, bool]:
    """(7,) Octo action -> ((7,) float64 robosuite OSC_POSE input in [-1, 1], whether anything was clipped)."""
    action = np.asarray(action, dtype=np.float64)
    if action.shape != (7,):
        raise ActionAdapterError(f"expected a (7,) action (dx, dy, dz, droll, dpitch, dyaw, gripper), got shape {action.shape}")
    if not np.all(np.isfinite(action)):
        raise ActionAdapterError(f"action contains NaN or inf: {action.tolist()}")

    position = action[:3] / config.position_max  # (3,)
    position_clipped = bool(np.any(np.abs(position) > 1.0))
    position = np.clip(position, -1.0, 1.0)

    rotation = rotation_delta_to_rotvec(action[3:6], config.rotation_convention) / config.rotation_max  # (3,)
    largest = float(np.max(np.abs(rotation)))
    rotation_clipped = largest > 1.0
    if rotation_clipped:
        rotation = rotation / largest

    openness = action[6] if config.gripper_open_value == 1.0 else 1.0 - action[6]
    if config.gripper_mode == "binary":
        gripper = -1.0 if openness >= config.gripper_threshold else 1.0
        gripper_clipped = False
    else:
        gripper = 1.0 - 2.0 * openness
        gripper_clipped = abs(gripper) > 1.0
        gripper = float(np.clip(gripper, -1.0, 1.0))

    osc = np.concatenate([position, rotation, [gripper]])
    return osc, position_clipped or rotation_clipped or gripper_clipped


def passthrough_action(action: np.ndarray) -> tuple[np.ndarray, bool]:
    """(7,) robosuite OSC_POSE input (6 arm values, gripper -1 open / +1 closed) -> (the same clipped to [-1, 1], clipped?).

    Values outside [-1, 1] are clipped (robosuite would clip them too) and reported, so the env can count them.
    """
    action = np.asarray(action, dtype=np.float64)
    if action.shape != (7,):
        raise ActionAdapterError(f"expected a (7,) robosuite action (6 arm values, gripper), got shape {action.shape}")
    if not np.all(np.isfinite(action)):
        raise ActionAdapterError(f"action contains NaN or inf: {action.tolist()}")
    clipped = bool(np.any(np.abs(action) > 1.0))
    return np.clip(action, -1.0, 1.0), clipped


def libero_action(action: np.ndarray) -> tuple[np.ndarray, bool]:
    """(7,) action in the convention of OpenVLA's LIBERO datasets -> (robosuite OSC_POSE input, clipped?).

    The 6 arm values are the OSC_POSE input itself (clipped to [-1, 1]); the gripper is 1 open / 0 closed and is
    binarised at 0.5 to LIBERO's -1 open / +1 closed, as OpenVLA's evaluation does (normalize_gripper_action with
    binarize, then the sign flip). A gripper of exactly 0.5 gives 0 (no command), as there.
    """
    action = np.asarray(action, dtype=np.float64)
    if action.shape != (7,):
        raise ActionAdapterError(f"expected a (7,) LIBERO action (6 arm values, gripper), got shape {action.shape}")
    if not np.all(np.isfinite(action)):
        raise ActionAdapterError(f"action contains NaN or inf: {action.tolist()}")
    clipped = bool(np.any(np.abs(action[:6]) > 1.0) or not 0.0 <= action[6] <= 1.0)
    osc = np.clip(action, -1.0, 1.0)
    osc[6] = -np.sign(2.0 * np.clip(action[6], 0.0, 1.0) - 1.0)
    return osc, clipped


def controller_action(action: np.ndarray, action_space: str, adapter: ActionAdapterConfig,
                      hold_gripper: float | None = None) -> tuple[np.ndarray, bool]:
    """A policy's action in `action_space` ("octo-delta", "robosuite", "libero") -> (OSC controller input, clipped),
    the one conversion every env applies. hold_gripper: the env takes 6-D arm actions and appends this gripper value."""
    if hold_gripper is not None:
        arm = np.asarray(action, np.float32).reshape(-1)
        if arm.shape != (6,):
            raise ValueError(f"this env holds the gripper at {hold_gripper:g} and takes 6-D actions, got {arm.shape[0]}-D")
        action = np.append(arm, np.float32(hold_gripper))
    if action_space == "robosuite":
        return passthrough_action(np.asarray(action))
    if action_space == "libero":
        return libero_action(np.asarray(action))
    return adapt_action(np.asarray(action), adapter)

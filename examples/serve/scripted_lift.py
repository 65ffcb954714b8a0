"""A blind scripted Lift expert: an example policy for standalone_server.py (numpy only, no simulator state).

It reads only the robot's 8-D low-dim state (the robosuite envs' `proprio`: end-effector position xyz in metres,
its orientation as extrinsic xyz Euler angles, the two finger joints) and drives robosuite's OSC_POSE input
(`--action-space robosuite`: 7 values, position then axis-angle rotation deltas in [-1, 1], gripper -1 open / +1
closed) with the saturated proportional law of the scripted demonstrators (reference_policies/experts.py): move
above the cube's nominal spot at the table centre, descend, close, lift. It never sees the cube, whose reset
placement varies by up to 3 cm, so it succeeds only when the cube lands near the centre. The phase is read from the
state itself (the finger gap and the height), so the policy is a pure function: the same observation gives the same
chunk, and it keeps no state between requests.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np

POSITION_MAX, ROTATION_MAX = 0.05, 0.5  # metres and radians per unit OSC input (robosuite's default output_max)
POSITION_GAIN, ROTATION_GAIN = 10.0, 2.0  # as the scripted demonstrators
TABLE_CENTRE = np.array([0.0, 0.0, 0.8])  # robosuite Lift's table_offset; the cube is placed within +-3 cm of it
GRASP_HEIGHT = 0.82  # metres: the cube's centre (half size 0.020-0.022 on the table top)
HOVER, LIFT = 0.07, 0.12  # metres above the grasp point: approach height, lift height
CENTRED = 0.01  # metres: horizontal error under which it descends
OPEN_GAP, GRIPPING_GAP = 0.07, 0.05  # metres between the fingers: open (0.08 when open); closed on the cube (0.04) or empty
STATE_KEYS = ("observation/state", "proprio", "state")  # the key the state comes under (openpi's, the harness's)


def _matrix(euler: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of extrinsic xyz Euler angles (scipy's Rotation.from_euler("xyz", ...))."""
    (cx, cy, cz), (sx, sy, sz) = np.cos(euler), np.sin(euler)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _rotvec(matrix: np.ndarray) -> np.ndarray:
    """(3,) axis-angle vector of a rotation matrix."""
    angle = float(np.arccos(np.clip((np.trace(matrix) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-6:
        return np.zeros(3)
    axis = np.array([matrix[2, 1] - matrix[1, 2], matrix[0, 2] - matrix[2, 0], matrix[1, 0] - matrix[0, 1]])
    norm = float(np.linalg.norm(axis))
    if norm < 1e-6:  # a half turn: the axis from the symmetric part
        axis = np.sqrt(np.clip((np.diag(matrix) + 1.0) / 2.0, 0.0, None))
        return axis * angle
    return axis / norm * angle


class BlindLiftExpert:
    """`infer(observation) -> {"actions": (action_horizon, 7) float32}` from the 8-D state alone."""

    def __init__(self, action_horizon: int = 4):
        self.action_horizon = int(action_horizon)
        parameters = {"table_centre": TABLE_CENTRE.tolist(), "grasp": GRASP_HEIGHT, "hover": HOVER, "lift": LIFT,
                      "gains": [POSITION_GAIN, ROTATION_GAIN], "gaps": [OPEN_GAP, GRIPPING_GAP],
                      "horizon": self.action_horizon}
        digest = hashlib.sha256(json.dumps(parameters, sort_keys=True).encode()).hexdigest()
        self.metadata = {"name": "blind-scripted-lift", "fingerprint": f"blind-scripted-lift/1:{digest[:16]}",
                         "action_horizon": self.action_horizon, "action_dim": 7, "action_space": "robosuite",
                         "state_keys": list(STATE_KEYS)}

    def state(self, observation: dict) -> np.ndarray:
        for key in STATE_KEYS:
            if key in observation:
                state = np.asarray(observation[key], np.float64).reshape(-1)[-8:]
                if state.shape != (8,):
                    raise ValueError(f"{key}: expected the 8-D state (eef xyz, Euler xyz, 2 fingers), got {state.shape}")
                return state
        raise ValueError(f"no state in the observation; send it under one of {list(STATE_KEYS)}")

    def action(self, state: np.ndarray) -> np.ndarray:
        """(7,) float32 OSC_POSE input for one state: the phase from where the hand is and how far its fingers are
        apart (the Panda resets them half open, about as far apart as when they hold the cube, so a closed hand
        away from the spot opens first)."""
        eef, euler, gap = state[:3], state[3:6], float(state[6] - state[7])
        grasp = np.array([TABLE_CENTRE[0], TABLE_CENTRE[1], GRASP_HEIGHT])
        off_centre = float(np.linalg.norm((grasp - eef)[:2]))
        low = eef[2] < GRASP_HEIGHT + 0.02
        if gap < GRIPPING_GAP and off_centre < 2 * CENTRED:  # closed over the spot (on the cube, or on nothing): lift
            target, gripper = grasp + [0.0, 0.0, LIFT], 1.0
        elif gap < OPEN_GAP and off_centre < CENTRED and low:  # closing at the grasp point: hold still
            target, gripper = eef, 1.0
        elif off_centre > CENTRED or gap < OPEN_GAP:  # elsewhere, or not yet open: open, go above the spot
            target, gripper = grasp + [0.0, 0.0, HOVER], -1.0
        elif eef[2] > GRASP_HEIGHT + 0.005:  # open above the spot: descend
            target, gripper = grasp, -1.0
        else:  # open at the grasp point: close
            target, gripper = eef, 1.0
        position = np.clip(POSITION_GAIN * (target - eef) / POSITION_MAX, -1.0, 1.0)
        current = _matrix(euler)
        yaw = float(np.arctan2(current[1, 0], current[0, 0]))  # keep the heading, point the gripper straight down
        wanted = _matrix(np.array([np.pi, 0.0, yaw]))
        rotation = np.clip(ROTATION_GAIN * _rotvec(wanted @ current.T) / ROTATION_MAX, -1.0, 1.0)
        return np.concatenate([position, rotation, [gripper]]).astype(np.float32)

    def infer(self, observation: dict) -> dict:
        """The chunk: this state's command repeated `action_horizon` times (a deterministic function of the state)."""
        action = self.action(self.state(observation))
        return {"actions": np.repeat(action[None], self.action_horizon, axis=0)}

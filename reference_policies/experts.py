"""Scripted demonstrators for Lift, Stack and PickPlaceCan, driving robosuite's OSC_POSE input directly.

An expert reads the end-effector pose from the observation's `proprio` and object poses from the
simulator (`RobosuiteEnv.object_poses` / `placement_targets`; a demonstrator may see the state) and
returns robosuite's own controller input: (7,) float32, arm values in [-1, 1] (position, then an
axis-angle rotation delta in the base frame, scaled by the controller's output limits), gripper -1 open,
+1 closed.

Each expert is a short list of phases (hover above the object, descend, close, lift, carry, lower,
release, retreat). Within a phase the arm follows a waypoint with a saturated proportional law
`clip(gain * error / output_max, -1, 1)`: robosuite's default OSC realises only about a quarter of a
commanded step per control step, so the gain is well above 1 and saturation keeps large moves at full
speed. The gripper's yaw turns to the nearest face of a cube (mod 90 degrees) and its roll/pitch stay as
at reset. A phase ends when its waypoint is reached within tolerance (or after its step budget).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

POSITION_MAX = 0.05  # metres per unit OSC input (robosuite 1.5 default output_max)
ROTATION_MAX = 0.5  # radians per unit OSC input
OPEN, CLOSED = -1.0, 1.0
EXPERT_TASKS = ("Lift", "Stack", "PickPlaceCan")


@dataclass(frozen=True)
class Phase:
    name: str
    gripper: float  # OPEN or CLOSED
    tolerance: float  # metres: the phase ends when the end effector is this close to its waypoint
    min_steps: int = 0  # stay at least this many steps (e.g. while the fingers close)
    max_steps: int = 80  # give up waiting and move on


@dataclass(frozen=True)
class ExpertConfig:
    position_gain: float = 10.0  # OSC units per (error / POSITION_MAX)
    rotation_gain: float = 2.0
    hover: float = 0.07  # metres above the grasp point before descending
    lift: float = 0.12  # metres to raise an object after grasping
    carry_height: float = 0.10  # Stack: clearance of cubeA's bottom above cubeB's top while carrying
    funnel: float = 3.0  # descending: metres of height kept per metre of horizontal misalignment
    # PickPlaceCan: metres the carry point sits nearer the robot than the can's target-bin centre, in x and in y.
    # The centre (x 0.1975) is beyond what the hand reaches at carrying height (x ~0.19): aiming there, the arm
    # pushed against its reach limit until the carry phase timed out, so one state was labelled both "push +x"
    # and "lower" (151 of 192 demonstrations, 12% of the frames) and the policy learned to push for ever.
    bin_inset: tuple[float, float] = (0.04, 0.04)


def _yaw_of(rotation: Rotation) -> float:
    """Heading (radians) of a frame's x axis in the world xy-plane."""
    x_axis = rotation.as_matrix()[:, 0]
    return float(np.arctan2(x_axis[1], x_axis[0]))


def _wrap(angle: float, period: float) -> float:
    """angle wrapped to [-period/2, period/2)."""
    return (angle + period / 2) % period - period / 2


class ScriptedExpert:
    """Waypoint state machine for one task; `reset(env)` at each episode, then `act(obs, env)` each step."""

    def __init__(self, task: str, config: ExpertConfig = ExpertConfig()):
        if task not in EXPERT_TASKS:
            raise ValueError(f"no scripted expert for task {task!r}; experts exist for {', '.join(EXPERT_TASKS)}")
        self.task = task
        self.config = config
        self.phases = _phases(task)
        self._phase = 0
        self._steps_in_phase = 0
        self._orientation: Rotation | None = None
        self._grasp_offset = np.zeros(3)

    @property
    def phase(self) -> str:
        return self.phases[min(self._phase, len(self.phases) - 1)].name

    def reset(self, obs: dict, env) -> None:
        """New episode: remember the reset orientation, aligned in yaw to the object to grasp."""
        self._phase = 0
        self._steps_in_phase = 0
        current = Rotation.from_euler("xyz", obs["proprio"][3:6])
        name, (_, quat) = self._grasp_object(env)
        if self.task in ("Lift", "Stack"):  # cubes: turn to the nearest face (90-degree symmetry)
            delta = _wrap(_yaw_of(Rotation.from_quat(quat)) - _yaw_of(current), np.pi / 2)
        else:  # the can is round
            delta = 0.0
        self._orientation = Rotation.from_euler("z", delta) * current
        self._grasp_offset = np.zeros(3)

    def _grasp_object(self, env) -> tuple[str, tuple[np.ndarray, np.ndarray]]:
        poses = env.object_poses()
        name = {"Lift": "cube", "Stack": "cubeA", "PickPlaceCan": "Can"}[self.task]
        return name, poses[name]

    def _waypoint(self, phase: str, eef: np.ndarray, env) -> np.ndarray:
        """(3,) end-effector target of `phase` from the current state."""
        cfg = self.config
        poses = env.object_poses()
        name, (obj, _) = self._grasp_object(env)
        up = np.array([0.0, 0.0, 1.0])
        if phase == "hover":
            return obj + up * cfg.hover
        if phase == "descend":
            return _funnel(obj, eef, cfg)
        if phase == "close":
            return obj
        if phase == "lift":
            return self._lift_target
        if self.task == "Stack":
            base = poses["cubeB"][0]
            # cubeA half size 0.02, cubeB half size 0.025 (robosuite's Stack): cubeA centre rests 0.045 above cubeB's
            rest = base + up * 0.045 + self._grasp_offset
            if phase == "carry":
                return rest + up * cfg.carry_height
            if phase == "lower":
                return rest + up * 0.012
            if phase == "release":
                return self._hold
            if phase == "retreat":
                return self._hold + up * 0.08
        if self.task == "PickPlaceCan":
            above = _bin_carry_point(env, name, cfg) + self._grasp_offset
            if phase == "carry":
                return above
            if phase == "lower":
                return above - up * BIN_LOWER
            if phase == "release":
                return self._hold
            if phase == "retreat":
                return self._hold + BIN_RETREAT
        return eef  # "hold": stay

    def act(self, obs: dict, env) -> np.ndarray:
        """(7,) float32 OSC_POSE input for the current observation."""
        if self._orientation is None:
            raise RuntimeError("call reset(obs, env) at the start of each episode")
        eef = np.asarray(obs["proprio"][:3], np.float64)
        phase = self.phases[min(self._phase, len(self.phases) - 1)]
        if self._steps_in_phase == 0:
            self._enter(phase.name, eef, env)
        target = self._waypoint(phase.name, eef, env)
        error = target - eef
        done = np.linalg.norm(error) < phase.tolerance and self._steps_in_phase >= phase.min_steps
        if (done or self._steps_in_phase >= phase.max_steps) and self._phase < len(self.phases) - 1:
            self._phase += 1
            self._steps_in_phase = 0
            return self.act(obs, env)
        self._steps_in_phase += 1
        return _command(error, obs["proprio"], self._orientation, phase.gripper, self.config)

    def _enter(self, phase: str, eef: np.ndarray, env) -> None:
        """Freeze what a phase needs from the moment it starts."""
        _, (obj, _) = self._grasp_object(env)
        if phase == "lift":
            self._grasp_offset = eef - obj  # where the object sits in the hand
            self._lift_target = eef + np.array([0.0, 0.0, self.config.lift])
        if phase in ("release", "retreat"):
            self._hold = eef.copy() if phase == "release" else self._hold


BIN_LOWER = 0.06  # PickPlaceCan: metres the hand descends from the carry point before releasing
BIN_RETREAT = np.array([0.0, -0.10, 0.05])  # PickPlaceCan: from the release point, up and back towards the robot


def _bin_carry_point(env, name: str, config: ExpertConfig) -> np.ndarray:
    """(3,) point high over object `name`'s target bin to carry it to: `config.bin_inset` nearer the robot than
    the bin's centre in x and y (the bin's region for the can spans x 0.10..0.295, y 0.28..0.525; its centre is
    near the edge of the Panda's reach), 20 cm above it, over the walls."""
    target = env.placement_targets()[name]
    dx, dy = config.bin_inset
    return np.array([target[0] - dx, target[1] - dy, target[2] + 0.20])


def _funnel(obj: np.ndarray, eef: np.ndarray, config: ExpertConfig) -> np.ndarray:
    """(3,) descend target: above the object by up to `hover`, higher while off-centre, so a misaligned gripper
    rises and re-centres before it reaches the object."""
    off_centre = float(np.linalg.norm((obj - eef)[:2]))
    return obj + np.array([0.0, 0.0, 1.0]) * min(config.hover, config.funnel * max(off_centre - 0.004, 0.0))


def _command(error: np.ndarray, proprio: np.ndarray, orientation: Rotation, gripper: float,
             config: ExpertConfig) -> np.ndarray:
    """(7,) float32 OSC_POSE input: the saturated proportional law towards a position `error` (3,) metres and
    the `orientation`, with the gripper command."""
    position = np.clip(config.position_gain * error / POSITION_MAX, -1.0, 1.0)
    current = Rotation.from_euler("xyz", proprio[3:6])
    rotvec = (orientation * current.inv()).as_rotvec()
    rotation = np.clip(config.rotation_gain * rotvec / ROTATION_MAX, -1.0, 1.0)
    return np.concatenate([position, rotation, [gripper]]).astype(np.float32)


class CanLabeller:
    """PickPlaceCan's expert as a function of the simulator state, for labelling states a policy visits (DAgger).

    `ScriptedExpert`'s phase follows its own progress, so it cannot say what to do from a state it did not
    lead to (a can carried past the bin, a missed grasp). This labeller reads the phase off the state with
    the same waypoints and control law:
      can over its bin and not held   -> retreat up and back from the release point, gripper open;
      can held, not over its bin      -> rise to carrying height, then carry to the expert's point over the bin;
      can held over its bin           -> centre on that point while high, lower, then open where the hand is;
      can elsewhere, not held         -> the descend funnel towards the can (hover height while off-centre),
                                         gripper open; close once the fingers are around the can; open again
                                         if they closed on nothing.
    """

    task = "PickPlaceCan"
    OBJECT = "Can"
    CLOSE_RADIUS = 0.015  # metres from the can's centre within which the fingers close (the expert stops at 0.008)
    EMPTY_FINGERS = 0.01  # summed finger opening below which closed fingers hold nothing (around the can: ~0.05)

    def __init__(self, config: ExpertConfig = ExpertConfig()):
        self.config = config
        self._orientation: Rotation | None = None

    def reset(self, obs: dict, env) -> None:
        """New episode: hold the reset orientation (the can is round: no yaw to align)."""
        self._orientation = Rotation.from_euler("xyz", obs["proprio"][3:6])

    def waypoint(self, obs: dict, env) -> tuple[np.ndarray, float]:
        """((3,) end-effector target, gripper command) for the current state."""
        up = np.array([0.0, 0.0, 1.0])
        eef = np.asarray(obs["proprio"][:3], np.float64)
        fingers = float(np.abs(np.asarray(obs["proprio"][6:8])).sum())
        can = env.object_poses()[self.OBJECT][0]
        above = _bin_carry_point(env, self.OBJECT, self.config)
        if env.grasping(self.OBJECT):
            above = above + (eef - can)  # the can, not the hand, goes over the bin
            lowered = above - up * BIN_LOWER
            off_bin = float(np.linalg.norm((above - eef)[:2]))
            if not env.over_placement(self.OBJECT):  # away from the bin: rise (as after the expert's lift), then carry
                if eef[2] < above[2] - 0.04:
                    return np.array([eef[0], eef[1], above[2]]), CLOSED
                return above, CLOSED
            if eef[2] > lowered[2] + 0.008:  # over the bin: centre at carrying height, then lower
                if off_bin > 0.012 and eef[2] > above[2] - 0.02:
                    return above, CLOSED
                return lowered, CLOSED
            return eef, OPEN  # lowered: release where the hand is
        if env.over_placement(self.OBJECT):
            return above - up * BIN_LOWER + BIN_RETREAT, OPEN  # retreat from the release point
        near = float(np.linalg.norm(can - eef)) < self.CLOSE_RADIUS
        if near and fingers > self.EMPTY_FINGERS:
            return can, CLOSED
        return _funnel(can, eef, self.config), OPEN

    def act(self, obs: dict, env) -> np.ndarray:
        """(7,) float32 OSC_POSE input the expert gives in this state."""
        if self._orientation is None:
            raise RuntimeError("call reset(obs, env) at the start of each episode")
        target, gripper = self.waypoint(obs, env)
        return _command(target - np.asarray(obs["proprio"][:3], np.float64), obs["proprio"], self._orientation,
                        gripper, self.config)


def _phases(task: str) -> tuple[Phase, ...]:
    grasp = (
        Phase("hover", OPEN, 0.012, max_steps=60),
        Phase("descend", OPEN, 0.008, max_steps=40),
        Phase("close", CLOSED, 1.0, min_steps=8, max_steps=8),
        Phase("lift", CLOSED, 0.02, max_steps=40),
    )
    if task == "Lift":
        return grasp + (Phase("hold", CLOSED, 0.0, max_steps=10**6),)
    return grasp + (
        Phase("carry", CLOSED, 0.012, max_steps=80),
        Phase("lower", CLOSED, 0.008, max_steps=40),
        Phase("release", OPEN, 1.0, min_steps=6, max_steps=6),
        Phase("retreat", OPEN, 0.0, max_steps=10**6),
    )

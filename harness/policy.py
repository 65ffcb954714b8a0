"""The closed loop every policy runs in: history window, resizing, per-step rng position, action-chunk execution.

One `ClosedLoopPolicy` serves one episode at a time (`reset` starts a new one). Each `step(obs)`:
env observation -> resized history window (padded as Octo's HistoryWrapper does) -> one `InferenceRequest` to the
policy's stateless batched inference (harness/policies: Octo's jitted `sample_actions`, or a policy server) -> the
action to execute now, chosen by temporal ensembling (infer every step, average the overlapping predictions) or a
receding horizon (execute k actions of a chunk per inference).

The state of an episode (`EpisodeState`: history, chunks, rng position, task) is kept apart from the stateless
inference, so a server can batch requests of many episodes (harness/run/workers.py, ray_executor.py, a policy server)
while the sequential runner uses the same code with batch 1.

Every low-dimensional key a policy reads is taken from the env observation and windowed and padded like the images
(its normalisation is the policy's). `check_env` compares the policy's inputs and action dimension with an env
before anything runs (one line per problem).
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from PIL import Image

from harness.octo.tokens import TokenMap
from harness.policy_config import PolicyConfig
from harness.probes.registry import active as active_probes


class EnvMismatchError(ValueError):
    """The model and the environment do not fit together (message: one line naming the fix)."""


@dataclass(frozen=True, eq=False)
class PolicyStep:
    action: np.ndarray  # (action_dim,) float32, the action to execute now
    chunk: np.ndarray  # (action_horizon, action_dim) float32, the chunk predicted at this step (unnormalised if stats)
    readout_attention: np.ndarray | None  # (layers, heads, readouts, keys) float32 of the inference that produced
    # `chunk`; None for a policy without attention (harness.policies.Capabilities)
    full_attention: np.ndarray | None  # (layers, heads, queries, keys) float32 or None
    inferred: bool  # False when a receding-horizon step reused an earlier chunk (attention is that chunk's)
    inference_seconds: float
    tokens: TokenMap | None = None  # what each attention key is (the layout of the inference that produced it)
    # what the policy was fed at this step: the newest history entry, image_* (height, width, 3) uint8 resized,
    # low-dim keys (dims,) float32 raw, exactly as they enter the observation window (harness.replay rebuilds it)
    inputs: dict | None = None
    # the per-step probes' payloads of this step's inference, keyed by probe name (harness.probes); {} when none ran
    probes: dict = dataclasses.field(default_factory=dict)


def resize_frame(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) uint8 -> (height, width, 3) uint8 with Lanczos filtering; unchanged when already that size."""
    if frame.shape[:2] == tuple(size):
        return frame
    return np.asarray(Image.fromarray(frame).resize((size[1], size[0]), Image.LANCZOS))


def ensemble(chunks: list[np.ndarray], weight: float) -> np.ndarray:
    """Temporal ensemble of the action for 'now'.

    chunks: oldest first, chunk i predicted len(chunks)-1-i steps ago, each (horizon, action_dim).
    Returns (action_dim,): weighted mean of chunk_i[age_i] with weights exp(-weight * i) (i = 0 oldest).
    """
    n = len(chunks)
    preds = np.stack([c[n - 1 - i] for i, c in enumerate(chunks)])  # (n, action_dim)
    w = np.exp(-weight * np.arange(n))
    return (preds * (w / w.sum())[:, None]).sum(axis=0).astype(np.float32)


@dataclass(frozen=True, eq=False)
class TaskPrompt:
    """What the model is asked at an episode (Octo's task): its instruction and/or the run's goal images; `key`
    identifies it for caching. A registered task (simulator, targets, limits) is `envs.taskspec.TaskSpec`."""

    instruction: str
    goals: dict[str, np.ndarray] | None = None  # {obs key: (height, width, 3) uint8} at the model's goal sizes
    key: tuple = ()

    @classmethod
    def of(cls, instruction: str | None, goals: dict[str, np.ndarray] | None = None) -> "TaskPrompt":
        digest = None
        if goals is not None:
            h = hashlib.sha1()
            for k in sorted(goals):
                h.update(k.encode() + np.ascontiguousarray(goals[k]).tobytes())
            digest = h.hexdigest()
        return cls(instruction or "", goals, (instruction or "", digest))


@dataclass(frozen=True, eq=False)
class InferenceRequest:
    """One episode's input to a batched inference call (no batch axis)."""

    observation: dict  # image_* (window, H, W, 3) uint8, low-dim keys (window, dims) float32 as the env gives them
    # (normalised by the inference side), timestep_pad_mask (window,) bool, pad_mask_dict {k: (window,)}
    task: TaskPrompt
    seed: int  # the episode's rng stream: key = fold_in(PRNGKey(seed), step)
    step: int
    # the env's masks of the current frame {obs key: {name: (h, w) bool}} (env convention), only at the steps of a
    # probe that needs them (harness.probes.Probe.needs_masks)
    masks: dict | None = None


@dataclass(frozen=True, eq=False)
class InferenceResult:
    """What one inference gives one episode."""

    chunk: np.ndarray  # (action_horizon, action_dim) float32
    readout_attention: np.ndarray | None  # (layers, heads, readouts, keys) float32; None: the policy gives no attention
    full_attention: np.ndarray | None  # (layers, heads, queries, keys) float32 or None
    seconds: float  # wall time of the batched call that produced it
    tokens: TokenMap | None = None  # what each attention key is
    observed: dict | None = None  # {obs key: (H, W, 3) uint8} current frames an intervention changed (masked)
    probes: dict = dataclasses.field(default_factory=dict)  # {probe name: payload} of the probes due at this step


def window_from_entries(entries: list[dict], window: int, keys: list[str]) -> dict:
    """The observation window after the last of `entries` (oldest first): image_* (window, H, W, 3), low-dim
    (window, dims), timestep_pad_mask (window,) and pad_mask_dict, left-padded with the first entry as Octo's
    HistoryWrapper does. `EpisodeState` and replay (harness/gate/replay.py) build windows with this one function."""
    frames = list(entries[-window:])
    n = len(frames)
    frames = [frames[0]] * (window - n) + frames  # left-pad with the first observation
    pad = np.arange(window) >= window - n  # (window,) False for padded slots
    obs = {k: np.stack([f[k] for f in frames]) for k in keys}
    obs["timestep_pad_mask"] = pad
    obs["pad_mask_dict"] = {k: pad for k in keys}
    return obs


def input_digest(value: np.ndarray) -> int:
    """64-bit blake2b of an input array's dtype, shape and bytes (the per-step fingerprint of what the policy saw)."""
    array = np.ascontiguousarray(value)
    h = hashlib.blake2b(digest_size=8)
    h.update(f"{array.dtype.str}{array.shape}".encode())
    h.update(array.tobytes())
    return int.from_bytes(h.digest(), "little")


class EpisodeState:
    """Everything one episode carries between control steps: history window, action-chunk state, rng position, task.

    `observe(obs)` returns either the `PolicyStep` to execute now (a receding-horizon step reusing a
    chunk) or an `InferenceRequest`; the result of that request goes to `complete(result)`.
    """

    def __init__(self, image_sizes: dict[str, tuple[int, int]], window: int, action_horizon: int, config: PolicyConfig,
                 task: TaskPrompt, seed: int, lowdim_sizes: dict[str, int] | None = None):
        self.image_sizes = dict(image_sizes)
        self.lowdim_sizes = dict(lowdim_sizes or {})  # low-dim obs key -> dims
        self.window = int(window)
        self.config = config
        self.task = task
        self.seed = int(seed)
        self.t = 0  # control steps taken
        self._history: deque = deque(maxlen=self.window)
        self._chunks: deque = deque(maxlen=int(action_horizon))
        self._pending: list[np.ndarray] = []
        self._last: PolicyStep | None = None
        self._entry: dict | None = None  # the history entry of the current step

    def _observation_window(self) -> dict:
        """History -> image_* (window, H, W, 3), timestep_pad_mask (window,), pad_mask_dict; left-padded as HistoryWrapper."""
        return window_from_entries(list(self._history), self.window, [*self.image_sizes, *self.lowdim_sizes])

    def observe(self, observation: dict[str, np.ndarray], masks: dict | None = None) -> "InferenceRequest | PolicyStep":
        check_observation(observation, self.image_sizes, self.lowdim_sizes)
        entry = {k: resize_frame(observation[k], s) for k, s in self.image_sizes.items()}
        entry.update({k: np.asarray(observation[k], np.float32) for k in self.lowdim_sizes})
        self._history.append(entry)
        self._entry = entry
        if self.config.execution == "receding_horizon" and self._pending:
            self.t += 1
            last = self._last
            return PolicyStep(self._pending.pop(0), last.chunk, last.readout_attention, last.full_attention, False, 0.0,
                              last.tokens, entry)
        masked = [probe for probe in active_probes(self.config) if probe.needs_masks and probe.due(self.config, self.t)]
        if masked and masks is None:
            raise EnvMismatchError(masked[0].masks_error)
        return InferenceRequest(self._observation_window(), self.task, self.seed, self.t,
                                masks if masked else None)  # sent to the server only when used

    def complete(self, result: InferenceResult, seconds: float | None = None) -> PolicyStep:
        """The action to execute now from this step's inference; `seconds` overrides the recorded inference time."""
        chunk = result.chunk
        if result.observed:  # an intervention masked the current frames: the history holds what the policy saw
            self._history[-1].update(result.observed)
        self.t += 1
        if self.config.execution == "receding_horizon":
            k = min(self.config.receding_steps, chunk.shape[0])
            self._pending = [chunk[i] for i in range(1, k)]
            action = chunk[0]
        else:
            self._chunks.append(chunk)
            action = ensemble(list(self._chunks), self.config.ensemble_weight)
        elapsed = result.seconds if seconds is None else seconds
        payloads = dict(result.probes)
        for probe in active_probes(self.config):  # a probe its sink computes: this inferred step is probed when due
            if not probe.in_inference(self.config) and probe.due(self.config, self.t - 1):
                payloads.setdefault(probe.name, {})
        self._last = PolicyStep(action, chunk, result.readout_attention, result.full_attention, True, elapsed, result.tokens,
                                self._entry, payloads)
        return self._last


class ClosedLoopPolicy:
    """Closed-loop policy for one episode at a time: `reset(instruction, seed)` then `step(obs)` every control step.

    `shape` is what the env side needs of the policy (image_sizes, lowdim_sizes, window_size, action_horizon: a
    `harness.policies.Policy` or a picklable copy); `infer` maps a list of InferenceRequests to InferenceResults: the
    policy's own batched inference in this process, or a client of a batching server an executor runs. Either way
    the episode's state (`EpisodeState`) and the per-example rng make the actions the same. Made by
    `Policy.closed_loop` (harness/policies).
    """

    def __init__(self, shape, config: PolicyConfig, infer):
        self.config = config
        self.window = int(shape.window_size)
        self.image_sizes = dict(shape.image_sizes)  # obs key -> (height, width)
        self.lowdim_sizes = dict(getattr(shape, "lowdim_sizes", None) or {})  # low-dim obs key -> dims
        self.action_horizon = int(shape.action_horizon)
        self._infer = infer
        self.dataset_key = getattr(infer, "dataset_key", None)  # the unnormalisation statistics the inference side uses
        self.action_dim = getattr(infer, "action_dim", None)  # dims of the actions handed to the env (None: unknown here)
        self._state: EpisodeState | None = None

    def reset(self, instruction: str | None = None, seed: int = 0, goals: dict[str, np.ndarray] | None = None) -> None:
        """Start an episode: its task (language encoded once, by the inference side) and its rng stream."""
        self._state = EpisodeState(self.image_sizes, self.window, self.action_horizon, self.config,
                                   TaskPrompt.of(instruction, goals), seed, self.lowdim_sizes)

    def check_env(self, env) -> None:
        """One-line EnvMismatchError when `env` lacks an input of the model or takes another action dimension."""
        check_env(self.image_sizes, self.lowdim_sizes, self.action_dim, env)

    def step(self, observation: dict[str, np.ndarray], masks: dict | None = None) -> PolicyStep:
        """observation: env dict with image_* (H, W, 3) uint8 -> the action to execute now (+ attention when inferred);
        masks: the env's masks of this observation (info["masks"]), used only at the steps of a probe that needs them."""
        decision = self._state.observe(observation, masks)
        if isinstance(decision, PolicyStep):
            return decision
        start = time.perf_counter()
        (result,) = self._infer([decision])
        return self._state.complete(result, time.perf_counter() - start)


# ---------------------------------------------------------------------------------------------- model <-> env fit

ENV_LOWDIM_HELP = "the robosuite envs give 'proprio' (8-D: end-effector position, xyz Euler angles, 2 finger joints)"


def check_observation(observation: dict, image_sizes: dict, lowdim_sizes: dict) -> None:
    """One-line EnvMismatchError when an observation lacks a model input or a low-dim input has other dims."""
    missing = [k for k in image_sizes if k not in observation]
    if missing:
        raise EnvMismatchError(f"the model needs camera observation(s) {missing}; give the env those cameras "
                               f"(e.g. --camera {missing[0]}=agentview:{image_sizes[missing[0]][0]})")
    for key, dims in lowdim_sizes.items():
        if key not in observation:
            raise EnvMismatchError(f"the model reads low-dim observation {key!r} ({dims}-D) which the env does not give; "
                                   f"{ENV_LOWDIM_HELP}: use a checkpoint whose LowdimObsTokenizer reads 'proprio' "
                                   f"or add {key!r} to the env's observations")
        got = int(np.shape(observation[key])[-1]) if np.ndim(observation[key]) else 1
        if got != dims:
            raise EnvMismatchError(f"the model reads {key!r} as {dims}-D but the env gives {got}-D; "
                                   f"{ENV_LOWDIM_HELP}: finetune on the env's layout")


def check_env(image_sizes: dict, lowdim_sizes: dict, action_dim: int | None, env) -> None:
    """Model inputs against `env.observation_space`, and the action dimension against `env.action_space`."""
    spaces = getattr(getattr(env, "observation_space", None), "spaces", None)
    if spaces is not None:
        check_observation({k: np.zeros(space.shape, np.float32) for k, space in spaces.items()},
                          {k: s for k, s in image_sizes.items()}, lowdim_sizes)
    env_dim = getattr(getattr(env, "action_space", None), "shape", None)
    if action_dim is not None and env_dim is not None and tuple(env_dim) != (action_dim,):
        config = getattr(getattr(env, "unwrapped", env), "config", None)
        kind = getattr(config, "action_space", "this")
        held = getattr(config, "hold_gripper", None)
        if held is not None and action_dim == env_dim[0] + 1:
            fix = "drop --hold-gripper (the model has its own gripper dimension)"
        elif held is None and action_dim == 6 and tuple(env_dim) == (7,):
            fix = ("run it with --hold-gripper open|closed|VALUE: the env then takes the 6 arm values and holds the "
                   "gripper there (recorded in the protocol)")
        else:
            fix = f"evaluate with a {env_dim[0]}-D action head (or statistics)"
        raise EnvMismatchError(f"the model's actions are {action_dim}-D but the env's {kind!r} action space takes "
                               f"{env_dim[0]}-D; {fix}")

"""Closed-loop policy around the Octo runtime: history window, resizing, per-step rng, action-chunk execution.

One `OctoPolicy` serves one episode at a time (`reset` starts a new one). Each `step(obs)`:
env observation -> resized history window (padded as Octo's HistoryWrapper does) -> one jitted
`sample_actions` call (actions + attention) -> the action to execute now, chosen by temporal
ensembling (infer every step, average the overlapping predictions) or a receding horizon
(execute k actions of a chunk per inference).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import jax
import numpy as np
from PIL import Image


@dataclass(frozen=True)
class PolicyConfig:
    execution: str = "temporal_ensemble"  # "temporal_ensemble" | "receding_horizon"
    receding_steps: int = 1  # actions executed per inference when execution == "receding_horizon"
    ensemble_weight: float = 0.0  # temporal ensemble: weight exp(-w * age_rank), 0 = plain average (Octo's default)
    dataset_key: str | None = None  # unnormalisation statistics key; None = model's default choice
    full_attention: bool = False  # also return (layers, heads, queries, keys) matrices (needed by attention rollout)

    def __post_init__(self) -> None:
        if self.execution not in ("temporal_ensemble", "receding_horizon"):
            raise ValueError(f"unknown execution {self.execution!r}; use 'temporal_ensemble' or 'receding_horizon'")
        if self.receding_steps < 1:
            raise ValueError("receding_steps must be >= 1")

    def describe(self) -> str:
        if self.execution == "receding_horizon":
            return f"receding_horizon:{self.receding_steps}"
        return f"temporal_ensemble:{self.ensemble_weight:g}"


@dataclass(frozen=True, eq=False)
class PolicyStep:
    action: np.ndarray  # (action_dim,) float32, the action to execute now
    chunk: np.ndarray  # (action_horizon, action_dim) float32, the chunk predicted at this step (unnormalised if stats)
    readout_attention: np.ndarray  # (layers, heads, readouts, keys) float32 of the inference that produced `chunk`
    full_attention: np.ndarray | None  # (layers, heads, queries, keys) float32 or None
    inferred: bool  # False when a receding-horizon step reused an earlier chunk (attention is that chunk's)
    inference_seconds: float


def default_dataset_key(model) -> str | None:
    """The unnormalisation key used when none is given: 'bridge_dataset' if present, else the only key, else None."""
    keys = sorted(getattr(model, "dataset_statistics", {}) or {})
    if not keys:
        return None
    if "bridge_dataset" in keys:
        return "bridge_dataset"
    if len(keys) == 1:
        return keys[0]
    raise ValueError(f"the model has several dataset statistics ({', '.join(keys[:8])}...); choose one with --dataset-key")


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


class OctoPolicy:
    """Stateful per-episode wrapper; `reset(instruction, seed)` then `step(obs)` every control step."""

    def __init__(self, model, config: PolicyConfig):
        self.model = model
        self.config = config
        self.window = int(model.window_size)
        self.image_sizes = dict(model.image_sizes)  # obs key -> (height, width)
        self.dataset_key = config.dataset_key if config.dataset_key is not None else default_dataset_key(model)
        self.statistics = model.unnormalization_statistics(self.dataset_key) if self.dataset_key else None
        self._history: deque = deque(maxlen=self.window)
        self._chunks: deque = deque(maxlen=int(model.action_horizon))
        self._task = None
        self._key = None
        self._t = 0
        self._pending: list[np.ndarray] = []
        self._last: PolicyStep | None = None

    def reset(self, instruction: str | None = None, seed: int = 0, goals: dict[str, np.ndarray] | None = None) -> None:
        """Start an episode: build the task once (language encoded once) and seed the per-step rng stream."""
        if goals is not None:
            self._task = self.model.create_task(goals={k: v[None] for k, v in goals.items()})
        else:
            self._task = self.model.create_task(texts=[instruction or ""])
        self._key = jax.random.PRNGKey(seed)
        self._history.clear()
        self._chunks.clear()
        self._pending = []
        self._last = None
        self._t = 0

    def _observation_batch(self) -> dict:
        """History deque -> Octo observation dict with batch 1: image_* (1, window, H, W, 3), timestep_pad_mask (1, window)."""
        n = len(self._history)
        frames = [self._history[0]] * (self.window - n) + list(self._history)  # left-pad with the first observation
        pad = np.arange(self.window) >= self.window - n  # (window,) False for padded slots
        obs = {k: np.stack([f[k] for f in frames])[None] for k in self.image_sizes}
        obs["timestep_pad_mask"] = pad[None]
        obs["pad_mask_dict"] = {k: pad[None] for k in self.image_sizes}
        return obs

    def step(self, observation: dict[str, np.ndarray]) -> PolicyStep:
        """observation: env dict with image_* (H, W, 3) uint8 -> the action to execute now (+ attention when inferred)."""
        missing = [k for k in self.image_sizes if k not in observation]
        if missing:
            raise KeyError(f"the model needs observation keys {missing}; configure the env cameras to provide them")
        self._history.append({k: resize_frame(observation[k], s) for k, s in self.image_sizes.items()})
        receding = self.config.execution == "receding_horizon"
        if receding and self._pending:
            self._t += 1
            last = self._last
            return PolicyStep(self._pending.pop(0), last.chunk, last.readout_attention, last.full_attention, False, 0.0)

        rng = jax.random.fold_in(self._key, self._t)
        start = time.perf_counter()
        actions, attention = self.model.sample_actions(
            self._observation_batch(), self._task, rng, self.statistics, full_attention=self.config.full_attention
        )
        chunk = np.asarray(actions[0], dtype=np.float32)  # (horizon, action_dim)
        readout = np.asarray(attention.readout[0], dtype=np.float32)  # (layers, heads, readouts, keys)
        full = None if attention.full is None else np.asarray(attention.full[0], dtype=np.float32)
        elapsed = time.perf_counter() - start
        self._t += 1
        if receding:
            k = min(self.config.receding_steps, chunk.shape[0])
            self._pending = [chunk[i] for i in range(1, k)]
            action = chunk[0]
        else:
            self._chunks.append(chunk)
            action = ensemble(list(self._chunks), self.config.ensemble_weight)
        self._last = PolicyStep(action, chunk, readout, full, True, elapsed)
        return self._last

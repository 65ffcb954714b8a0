"""Is a model's output on the same inputs the same? Pure maths of `octo-harness replay` (harness/gate/replay.py).

Open loop on recorded inputs, the only differences between two forward passes are the model's and the
float arithmetic's (instruction set, XLA version, batch shape): the closed loop, which turns a 1e-6 change
into another trajectory, is taken out. Per inferred step:

- `action_change`: max over the chunk of |a - b| in normalised action units (divided by the statistics' std
  for "normal", by half the p01..p99 range for "bounds"; dimensions the statistics' mask excludes, and
  models without statistics, raw), so one tolerance fits every action dimension and model;
- attention change: Jensen-Shannon divergence (bits) of the readout attention per layer and head
  (`attention_divergence`), both sides rounded to float16 as attention.npz stores them.

`Tolerances` are derived from measured float32 noise across instruction sets (README "Replay"): the
reference policy's recorded Lift episodes (10 x up to 80 steps), recorded under AVX-512, `XLA_FLAGS=
--xla_cpu_max_isa=SSE4_2` and `=AVX` and replayed under each of the others, differ by at most 2.8e-5
normalised units and 3.2e-8 bits (step 0 alone: ~1e-6 and ~1e-9; on the recording platform: exactly 0).
ACTION_NOISE and ATTENTION_NOISE round those up and the tolerances are 10x them. Gaussian noise of std 1e-3
added to one MLP kernel changes the step-0 chunk by 1.2e-3 (4x the tolerance; 1.1e-2 at its largest step)
and attention by 7.8e-6 bits (22x) (tests/gate/test_replay.py). A step is EQUIVALENT when both changes are
within tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


ACTION_NOISE = 3e-5  # measured max |change| (normalised units) across ISAs on the reference policy's episodes
ATTENTION_NOISE = 3.5e-8  # measured max JS (bits) likewise (float16-rounded attention)
EPS = 1e-8


def jensen_shannon(p: np.ndarray, q: np.ndarray, axis: int = -1) -> np.ndarray:
    """Jensen-Shannon divergence in bits (0 = equal, 1 = disjoint support) between rows normalised along `axis`.

    p, q (..., keys) >= 0 -> (...). JS = H(m) - (H(p) + H(q)) / 2 with m = (p + q) / 2.
    """
    p = np.asarray(p, np.float64)
    q = np.asarray(q, np.float64)
    p = p / np.maximum(p.sum(axis=axis, keepdims=True), 1e-300)
    q = q / np.maximum(q.sum(axis=axis, keepdims=True), 1e-300)
    m = 0.5 * (p + q)

    def kl(a, b):
        ratio = np.divide(a, b, out=np.ones_like(a), where=(a > 0) & (b > 0))
        return (a * np.log2(ratio)).sum(axis=axis)

    return np.clip(0.5 * kl(p, m) + 0.5 * kl(q, m), 0.0, 1.0)


def attention_divergence(base: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """readout attention (..., layers, heads, readouts, keys) x2 -> (..., layers, heads) JS in bits, mean over readouts."""
    return jensen_shannon(base, cand).mean(axis=-1)


@dataclass(frozen=True)
class Tolerances:
    action: float = 10 * ACTION_NOISE  # max |change| of the action chunk, normalised units
    attention_js: float = 10 * ATTENTION_NOISE  # max JS divergence (bits) of any layer's and head's readout row

    def __post_init__(self):
        if not (self.action >= 0 and self.attention_js >= 0):
            raise ValueError(f"replay tolerances must be >= 0, got {self.action} and {self.attention_js}")


def action_scale(statistics: dict | None, kind: str, dims: int) -> np.ndarray:
    """(dims,) divisor that turns an action difference into normalised units (see the module docstring)."""
    scale = np.ones(dims, np.float64)
    if not statistics:
        return scale
    if kind == "bounds" and "p01" in statistics and "p99" in statistics:
        spread = (np.asarray(statistics["p99"], np.float64) - np.asarray(statistics["p01"], np.float64)) / 2
    elif "std" in statistics:
        spread = np.asarray(statistics["std"], np.float64)
    else:
        return scale
    if spread.shape != (dims,):
        return scale
    mask = np.asarray(statistics.get("mask", np.ones(dims, bool)), bool)
    return np.where(mask, spread + EPS, 1.0)


def action_change(recorded: np.ndarray, replayed: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """chunks (steps, horizon, dims) x2, scale (dims,) -> (steps,) max |difference| in normalised units."""
    diff = np.abs(np.asarray(replayed, np.float64) - np.asarray(recorded, np.float64)) / scale
    return diff.reshape(diff.shape[0], -1).max(axis=1) if diff.size else np.zeros(diff.shape[0])


def attention_change(recorded: np.ndarray, replayed: np.ndarray) -> np.ndarray:
    """readout attention (steps, layers, heads, readouts, keys) x2 -> (steps, layers, heads) JS in bits, both sides
    rounded to float16 first (the precision attention.npz keeps)."""
    a = np.asarray(recorded, np.float16).astype(np.float64)
    b = np.asarray(replayed, np.float16).astype(np.float64)
    return attention_divergence(a, b)


def first_change(actions: np.ndarray, js: np.ndarray, tolerances: Tolerances) -> int | None:
    """actions (steps,), js (steps, layers, heads) -> index of the first step beyond a tolerance (NaN counts as
    beyond: a model that outputs NaN has changed), or None."""
    js_max = np.max(js.reshape(js.shape[0], -1), axis=1, initial=0.0)  # NaN propagates: a NaN output is a change
    beyond = ~(actions <= tolerances.action) | ~(js_max <= tolerances.attention_js)
    hits = np.flatnonzero(beyond)
    return int(hits[0]) if hits.size else None

"""Action consistency, pure numpy: how much an action chunk disagrees with what the episode's earlier chunks planned
for the same future steps, and the spread of chunks sampled again from the same inputs. In the action space's units
(the unnormalised actions handed to the env: actions.npz's `predicted`).

Disagreement at an inferred step t with chunk C_t (horizon H, dims d): every earlier chunk C_s inferred at a step
s = t - a with age 1 <= a < H planned steps t .. s + H - 1, which C_t predicts too: C_t[i] against C_s[a + i] for
i = 0 .. H - 1 - a. Per age a, the mean absolute difference over those H - a steps and the d dims (`by_age`, nan
where no chunk of that age was inferred: a receding horizon infers every k-th step); over every overlapping pair of
every age, its mean per dim (`dims`) and overall (`disagreement`: each pair of predictions of one future step and
dim counts once, so the recent chunks, which overlap most, weigh most). nan at a step with no overlapping chunk
(the first step; a receding horizon of k >= H steps).

7-D actions (every built-in action space: octo-delta, robosuite, LIBERO) are (3 translation, 3 rotation, 1 gripper):
`PARTS` names the dims whose means are reported apart.

Spread (sampling heads): the element-wise standard deviation (ddof 0) over the executed chunk and K more drawn from
the same inputs with other rng keys, averaged over the horizon per dim (`spread_dims`) and overall (`spread`).
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

PARTS = {"translation": slice(0, 3), "rotation": slice(3, 6), "gripper": slice(6, 7)}  # of 7-D actions


def parts(dims: np.ndarray) -> dict[str, float]:
    """{translation, rotation, gripper: the mean over their dims} of a 7-D per-dim value ({} for other dims)."""
    dims = np.asarray(dims, np.float64)
    if dims.shape[-1] != 7:
        return {}
    return {name: float(np.mean(dims[..., where])) for name, where in PARTS.items()}


def disagreement(chunk: np.ndarray, earlier: Iterable[tuple[int, np.ndarray]]) -> dict:
    """chunk (H, d) inferred now; earlier: (age in steps, that chunk (H, d)) of the episode's earlier inferred chunks
    (any ages; those of age < 1 or >= H do not overlap) -> {"disagreement": float, "dims": (d,), "by_age": (H - 1,)}
    (float64; nan without overlap)."""
    chunk = np.asarray(chunk, np.float64)
    horizon, dim = chunk.shape
    by_age = np.full(max(horizon - 1, 0), np.nan)
    total = np.zeros(dim)
    count = 0
    for age, previous in earlier:
        age = int(age)
        if not 1 <= age < horizon:
            continue
        diff = np.abs(chunk[:horizon - age] - np.asarray(previous, np.float64)[age:])  # (H - age, d)
        by_age[age - 1] = float(diff.mean())
        total += diff.sum(axis=0)
        count += horizon - age
    dims = total / count if count else np.full(dim, np.nan)
    return {"disagreement": float(dims.mean()) if count else float("nan"), "dims": dims, "by_age": by_age}


class ChunkHistory:
    """An episode's inferred chunks in step order (`add(step, chunk)`), and the disagreement of one of them with the
    earlier ones (`at(step)`); only the last H - 1 steps' chunks are kept."""

    def __init__(self):
        self.chunks: dict[int, np.ndarray] = {}

    def add(self, step: int, chunk: np.ndarray) -> None:
        chunk = np.asarray(chunk, np.float32)
        self.chunks[int(step)] = chunk
        oldest = int(step) - chunk.shape[0] + 1
        for s in [s for s in self.chunks if s < oldest]:
            del self.chunks[s]

    def at(self, step: int) -> dict:
        chunk = self.chunks[int(step)]
        return disagreement(chunk, ((int(step) - s, c) for s, c in self.chunks.items() if s < int(step)))


def episode(steps: Sequence[int], predicted: np.ndarray, inferred: Sequence[bool] | None = None) -> dict[str, np.ndarray]:
    """An episode's consistency from its recorded chunks (actions.npz: step, predicted (n, H, d), inferred (n,); None:
    every step inferred), at every inferred step: {"step" (m,), "disagreement" (m,), "dims" (m, d), "by_age"
    (m, H - 1)} float64 (nan without overlap). What the probe's sink writes at its steps, for any run that kept its
    actions.npz, the probe on or not."""
    predicted = np.asarray(predicted, np.float32)
    flags = np.ones(len(steps), bool) if inferred is None else np.asarray(inferred, bool)
    history = ChunkHistory()
    rows = []
    for step, chunk, new in zip(steps, predicted, flags):
        if new:
            history.add(int(step), chunk)
            rows.append((int(step), history.at(int(step))))
    horizon, dim = predicted.shape[1:] if predicted.ndim == 3 else (0, 0)
    return {"step": np.asarray([s for s, _ in rows], int),
            "disagreement": np.asarray([r["disagreement"] for _, r in rows], np.float64),
            "dims": np.asarray([r["dims"] for _, r in rows], np.float64).reshape(len(rows), dim),
            "by_age": np.asarray([r["by_age"] for _, r in rows], np.float64).reshape(len(rows), max(horizon - 1, 0))}


def spread(chunks: np.ndarray) -> dict:
    """chunks (K + 1, H, d): the executed chunk and K drawn again -> {"spread": float, "spread_dims": (d,)} (float64):
    the element-wise standard deviation over the chunks, averaged over the horizon (per dim) and the dims."""
    std = np.asarray(chunks, np.float64).std(axis=0)  # (H, d)
    dims = std.mean(axis=0)
    return {"spread": float(dims.mean()), "spread_dims": dims}

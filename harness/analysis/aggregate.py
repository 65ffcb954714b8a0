"""Attention aggregation across steps and episodes: pure numpy functions, no files, no drawing.

Over the per-step measures of each episode (harness.measures.episode: `episode_measures`, stored by the writers in
attention.npz; metric names there), two stages, each a pure function:

- `summarise_episode`: per-step measures -> per-episode means (over steps) and means per bin of
  normalised episode progress (step t of n falls in bin floor(t * bins / n)).
- `aggregate_task`: the summaries of a task's episodes -> long-format rows (metric, layer, head, value,
  ci_low, ci_high, n) with percentile-bootstrap intervals over episodes, for all episodes and split by
  successful / unsuccessful episodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from harness.analysis.bootstrap import DEFAULT_RESAMPLES, bootstrap_mean_ci
from harness.measures.episode import EpisodeMeasures

OUTCOMES = ("all", "success", "no_success")  # episode subsets: every ok episode, those that succeeded, those that did not
HEAD_MEAN = "mean"  # the head label of layer-level (head-mean) rows


def nanmean(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """Mean over `axis` ignoring NaN; NaN where nothing is left (no warning)."""
    values = np.asarray(values, np.float64)
    present = np.isfinite(values)
    count = present.sum(axis=axis)
    total = np.where(present, values, 0.0).sum(axis=axis)
    return np.divide(total, count, out=np.full(np.shape(total), np.nan), where=count > 0)


def progress_bins(steps: int, bins: int) -> np.ndarray:
    """(steps,) bin of each step by normalised progress: step t of n falls in bin floor(t * bins / n)."""
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    return (np.arange(steps) * bins) // max(steps, 1)


def binned_mean(values: np.ndarray, bins: int) -> np.ndarray:
    """values (steps, ...) -> (bins, ...) NaN-ignoring mean per progress bin; empty bins (short episodes) are NaN."""
    values = np.asarray(values, np.float64)
    index = progress_bins(values.shape[0], bins)
    present = np.isfinite(values)
    total = np.zeros((bins, *values.shape[1:]))
    count = np.zeros((bins, *values.shape[1:]))
    np.add.at(total, index, np.where(present, values, 0.0))
    np.add.at(count, index, present)
    return np.divide(total, count, out=np.full(total.shape, np.nan), where=count > 0)


@dataclass(frozen=True, eq=False)
class EpisodeSummary:
    steps: int
    layer: dict[str, np.ndarray]  # metric -> (layers,) mean over steps
    head: dict[str, np.ndarray]  # metric -> (layers, heads) mean over steps
    progress: dict[str, np.ndarray]  # metric -> (bins, layers) mean per progress bin

    @property
    def layers(self) -> int:
        return int(next(iter(self.layer.values())).shape[0]) if self.layer else 0

    @property
    def heads(self) -> int:
        return int(next(iter(self.head.values())).shape[1]) if self.head else 0


def summarise_episode(measures: EpisodeMeasures, bins: int = 10) -> EpisodeSummary:
    """Per-step measures -> means over the episode's steps and per progress bin (NaN steps left out)."""
    return EpisodeSummary(
        steps=measures.steps,
        layer={k: nanmean(v) for k, v in measures.layer.items()},
        head={k: nanmean(v) for k, v in measures.head.items()},
        progress={k: binned_mean(v, bins) for k, v in measures.layer.items()},
    )


TABLE_COLUMNS = ("run", "task", "layer", "head", "metric", "value", "ci_low", "ci_high", "outcome", "n")
PROGRESS_COLUMNS = TABLE_COLUMNS + ("bin", "progress_from", "progress_to")


def _stack(summaries: list[EpisodeSummary], level: str, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """(episodes, *shape) values of one metric; NaN for episodes without it."""
    out = np.full((len(summaries), *shape), np.nan)
    for i, s in enumerate(summaries):
        value = getattr(s, level).get(name)
        if value is not None:
            if value.shape != shape:
                raise ValueError(f"episode {i} has {name} of shape {value.shape}, others {shape}: mixed models in one task, "
                                 "or kept episodes (scripts/keep_grid_runs.py: the last layer only) beside full ones; "
                                 "restore the kept copy into an empty folder and read that")
            out[i] = value
    return out


def aggregate_task(
    summaries: list[EpisodeSummary],
    successes: list[bool],
    run: str,
    task: str,
    confidence: float = 0.95,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
) -> dict[str, list[tuple]]:
    """Episodes of one task -> {"layers": rows, "heads": rows, "progress": rows} (tuples in TABLE_COLUMNS /
    PROGRESS_COLUMNS order): mean over episodes with a `confidence` percentile-bootstrap interval, for the
    outcomes "all", "success" and "no_success" (a subset without episodes gives no rows). `layer` and `head` are
    ints ("mean" for the head-mean level); the progress bin b covers progress [b/bins, (b+1)/bins).
    Metrics no episode has (e.g. mask metrics of a run without masks) give no rows.
    """
    if len(summaries) != len(successes):
        raise ValueError("one success flag per episode summary")
    out: dict[str, list[tuple]] = {"layers": [], "heads": [], "progress": []}
    if not summaries:
        return out
    layer_shape = {k: v.shape for s in summaries for k, v in s.layer.items()}
    head_shape = {k: v.shape for s in summaries for k, v in s.head.items()}
    prog_shape = {k: v.shape for s in summaries for k, v in s.progress.items()}
    blocks = (  # (level, table, metric -> shape)
        [("layer", "layers", k, sh) for k, sh in layer_shape.items()]
        + [("head", "heads", k, sh) for k, sh in head_shape.items()]
        + [("progress", "progress", k, sh) for k, sh in prog_shape.items()]
    )
    columns = [_stack(summaries, level, name, shape).reshape(len(summaries), -1) for level, _, name, shape in blocks]
    matrix = np.concatenate(columns, axis=1)  # (episodes, all columns)
    success = np.asarray(successes, bool)
    for outcome in OUTCOMES:
        pick = {"all": np.ones_like(success), "success": success, "no_success": ~success}[outcome]
        if not pick.any():
            continue
        mean, low, high, n = bootstrap_mean_ci(matrix[pick], confidence, resamples, seed)
        offset = 0
        for level, table, name, shape in blocks:
            size = int(np.prod(shape))
            m, lo, hi, cnt = (a[offset:offset + size].reshape(shape) for a in (mean, low, high, n))
            offset += size
            if not (cnt > 0).any():
                continue
            rows = out[table]
            if level == "layer":
                for li in range(shape[0]):
                    if cnt[li]:
                        rows.append((run, task, li, HEAD_MEAN, name, m[li], lo[li], hi[li], outcome, int(cnt[li])))
            elif level == "head":
                for li in range(shape[0]):
                    for h in range(shape[1]):
                        if cnt[li, h]:
                            rows.append((run, task, li, h, name, m[li, h], lo[li, h], hi[li, h], outcome, int(cnt[li, h])))
            else:
                bins = shape[0]
                for b in range(bins):
                    for li in range(shape[1]):
                        if cnt[b, li]:
                            rows.append((run, task, li, HEAD_MEAN, name, m[b, li], lo[b, li], hi[b, li], outcome,
                                         int(cnt[b, li]), b, b / bins, (b + 1) / bins))
    return out


def representative_index(values: np.ndarray) -> int:
    """values (episodes,) -> index of the episode closest to the median (first on ties; 0 when all are NaN)."""
    values = np.asarray(values, np.float64)
    if not np.isfinite(values).any():
        return 0
    distance = np.abs(values - np.nanmedian(values))
    return int(np.nanargmin(distance))


def headline_metric(names, cameras: list[str]) -> str | None:
    """The target-lift metric the report leads with: mask_lift/<camera>/target of the first camera that has it."""
    names = set(names)
    for obs in cameras:
        if f"mask_lift/{obs}/target" in names:
            return f"mask_lift/{obs}/target"
    return None

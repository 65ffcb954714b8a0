"""The predictors of an episode's failure from what is known up to step t, fitted on some seeds and scored on others.

Each predictor turns an episode's step t into inputs, and an L2-regularised logistic regression (stats.Logistic) on
them gives a failure score; every predictor is fitted per task:
  time and phase       the baseline: t, the phase at t and the furthest phase by t (one-hot), and the steps since the
                       furthest phase was reached (a stall by t)
  readout probe        the readout features at t (--readout-features-every): a linear probe
  action consistency   the chunk disagreement, mean over the last WINDOW steps up to t
  attention entropy    likewise, the attention entropy
  nuisance mass        likewise, the attention mass on background and distractors
Within conditions (the reported result), every predictor's inputs but the baseline's are centred per run (one
condition and level) by the mean of that run's training episodes, as harness.analysis.predictors centres per run:
what is left is the variation within a condition, which the perturbation alone cannot make. Pooled (labelled so),
the inputs are not centred.

Cross-fitting (`scores`): the seeds are split into folds (stats.seed_folds); the episodes of each fold are scored by
the model fitted on the other folds' episodes, so each score comes from a model that never saw that seed. A training
row is one (episode, step), each episode weighing 1 in all.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from harness.analysis.diagnose.signals import EpisodeSignals, window_mean
from harness.analysis.diagnose.stats import MIN_CLASS, Logistic, calibrate

BASELINE = "time and phase"
PREDICTORS = (BASELINE, "readout probe", "action consistency", "attention entropy", "nuisance mass")
SIGNAL_OF = {"action consistency": "consistency", "attention entropy": "entropy", "nuisance mass": "nuisance"}
WINDOW = 5
L2 = 1.0  # the penalty on the standardised weights, each training episode weighing 1
MAX_ROWS = 40_000  # training rows per fit at most: every k-th step of each episode beyond it


def baseline_inputs(episode: EpisodeSignals) -> np.ndarray:
    """(steps, 2 + 2 * (phases + 1) + 1): t, phase at t and furthest phase by t one-hot (unknown: the last column),
    steps since the furthest phase was reached."""
    n = episode.steps
    k = len(episode.phase_names) + 1
    phase = np.where(episode.phase >= 0, episode.phase, k - 1)
    known = np.where(episode.phase >= 0, episode.phase, -1)
    furthest = np.maximum.accumulate(known)
    reached = np.zeros(n)
    last = 0
    for t in range(n):
        if t == 0 or furthest[t] > furthest[t - 1]:
            last = t
        reached[t] = t - last
    furthest = np.where(furthest >= 0, furthest, k - 1)
    eye = np.eye(k)
    return np.column_stack([np.arange(n, dtype=np.float64), eye[phase], eye[furthest], reached])


def inputs(episode: EpisodeSignals, predictor: str) -> np.ndarray | None:
    """(steps, d) inputs of `predictor` at every step (nan rows where not known yet); None when the episode has none."""
    if predictor == BASELINE:
        return baseline_inputs(episode)
    if predictor == "readout probe":
        return None if episode.features is None else np.asarray(episode.features, np.float64)
    values = episode.signals[SIGNAL_OF[predictor]]
    if not np.isfinite(values).any():
        return None
    return window_mean(values, WINDOW)[:, None]


def available(episodes: list[EpisodeSignals], predictor: str) -> bool:
    return any(inputs(e, predictor) is not None for e in episodes)


def _centres(episodes, data, train: np.ndarray) -> dict:
    """{stratum: the mean input row of its training episodes' steps} (each episode weighing 1)."""
    sums: dict = {}
    for i in np.flatnonzero(train):
        x = data[i]
        if x is None:
            continue
        rows = x[np.isfinite(x).all(axis=1)]
        if len(rows):
            total, count = sums.get(episodes[i].stratum, (0.0, 0))
            sums[episodes[i].stratum] = (total + rows.mean(axis=0), count + 1)
    return {k: total / count for k, (total, count) in sums.items()}


@dataclass
class Fitted:
    """A predictor's cross-fitted scores over one task's episodes: `scores[i]` (steps,) from the model that did not
    see episode i's seed (None: no signal, or no model for its fold); `threshold[i]` that model's threshold at
    stats.FALSE_ALARM, calibrated on its successful training episodes only (nan: fewer than MIN_CLASS of them);
    `training_false_alarm[i]` the share of those successes it flags (at most FALSE_ALARM by construction)."""

    scores: list
    threshold: np.ndarray
    training_false_alarm: np.ndarray


def scores(episodes: list[EpisodeSignals], folds: np.ndarray, predictor: str, within: bool) -> Fitted:
    """Each episode's (steps,) failure score from the model fitted on the other folds (nan where its inputs are not
    known yet; None for an episode without the predictor's signal), and each fold's calibrated threshold. Episodes
    of one task."""
    data = [inputs(e, predictor) for e in episodes]
    failed = np.asarray([not e.success for e in episodes], float)
    out: list[np.ndarray | None] = [None] * len(episodes)
    threshold = np.full(len(episodes), np.nan)
    alarms = np.full(len(episodes), np.nan)
    total = sum(len(x) for x in data if x is not None)
    stride = max(1, int(np.ceil(total / MAX_ROWS)))
    centre = within and predictor != BASELINE
    for fold in np.unique(folds):
        train = folds != fold
        centres = _centres(episodes, data, train) if centre else {}

        def shifted(i):
            x = data[i]
            if x is None or not centre:
                return x
            return x - centres.get(episodes[i].stratum, np.nan)

        rows, labels, weights = [], [], []
        for i in np.flatnonzero(train):
            x = shifted(i)
            if x is None:
                continue
            x = x[::stride]
            keep = np.isfinite(x).all(axis=1)
            if keep.any():
                rows.append(x[keep])
                labels.append(np.full(int(keep.sum()), failed[i]))
                weights.append(np.full(int(keep.sum()), 1.0 / keep.sum()))
        if not rows:
            continue
        y = np.concatenate(labels)
        if y.min() == y.max():  # one class in training: no model, no scores for this fold
            continue
        model = Logistic(L2).fit(np.concatenate(rows), y, np.concatenate(weights))

        def scored(i):
            x = shifted(i)
            if x is None:
                return None
            score = np.full(len(x), np.nan)
            keep = np.isfinite(x).all(axis=1)
            if keep.any():
                score[keep] = model.score(x[keep])
            return score

        peaks = [np.nanmax(s) for s in (scored(i) for i in np.flatnonzero(train & (failed == 0)))
                 if s is not None and np.isfinite(s).any()]
        cut = calibrate(peaks) if len(peaks) >= MIN_CLASS else np.nan
        held_out = np.flatnonzero(~train)
        threshold[held_out] = cut
        alarms[held_out] = np.mean(np.asarray(peaks) > cut) if np.isfinite(cut) else np.nan
        for i in held_out:
            out[i] = scored(i)
    return Fitted(out, threshold, alarms)

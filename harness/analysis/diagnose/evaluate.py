"""How well, and how early, each predictor tells a failing episode from a succeeding one, on held-out seeds.

Per task (`evaluate_task`):
  by step   at t = 10, 25, 50, 100, over the episodes still running at t (their steps > t): each predictor's
            cross-fitted score at t. The reported AUROC is within conditions (pairs of one run only, inputs centred
            per run); the pooled AUROC (pairs across runs, inputs not centred) is labelled so.
  by phase  at the step each episode entered the phase, over the episodes that reached it.
Each AUROC has a seed-cluster bootstrap interval (stats.cluster_draws), and the same resamples give the interval of
its difference from the baseline's (time and phase): a predictor whose difference interval does not lie above 0 is
"not better than time and phase". With fewer than MIN_CLASS failures or successes, or no run holding both, the cell is
a line saying so, not a number.
  lead time  per predictor, the threshold its fold's model puts over the peak scores of at most 5% of its
            successful training episodes (stats.calibrate): the share of held-out failures it flags, the median
            steps from the first flag to the failure's stall step (positive: before the stall), and the share of
            held-out successes it flags (the false-alarm rate).
"""

from __future__ import annotations

import math

import numpy as np

from harness.analysis.diagnose import predictors as P
from harness.analysis.diagnose import stats as S
from harness.analysis.diagnose.signals import EpisodeSignals

STEPS = (10, 25, 50, 100)
BETTER, NOT_BETTER = "better than time and phase", "not better than time and phase"


def _value(score, step) -> float:
    return math.nan if score is None or step is None or step >= len(score) else float(score[step])


def too_few(failures: int, successes: int, where: str) -> str | None:
    """The line for a cell with too few of a class, None when both have at least MIN_CLASS."""
    if min(failures, successes) >= S.MIN_CLASS:
        return None
    short = "successes" if successes < failures else "failures"
    return (f"too few {short} {where} ({S.counted(successes, failures)}; at least {S.MIN_CLASS} of each "
            f"are needed): no AUROC")


def _interval(draws) -> list[float]:
    return list(S.percentile_interval(draws))


def moment(episodes: list[EpisodeSignals], at: list, fitted: dict, pooled: dict, weights: np.ndarray,
           fold: np.ndarray, where: str) -> dict:
    """One cell of the tables: each predictor's AUROC over the episodes with a step in `at` (None: left out), within
    conditions and pooled, with intervals and the verdict against the baseline. Only pairs scored by one fold's model
    are compared: across folds, the models' intercepts (and the per-run centres) differ with their training episodes'
    share of failures, which biases a pooled cross-validated AUROC below 0.5 for a useless score."""
    idx = [i for i, step in enumerate(at) if step is not None]
    failed = np.asarray([not episodes[i].success for i in idx], bool)
    strata = np.asarray(["\x00".join((*episodes[i].stratum, str(fold[i]))) for i in idx])
    folds = np.asarray([fold[i] for i in idx])
    out = {"where": where, "failures": int(failed.sum()), "successes": int((~failed).sum()), "predictors": {}}
    message = too_few(out["failures"], out["successes"], where)
    if message:
        out["message"] = message
        return out
    both = [k for k in np.unique(strata) if failed[strata == k].any() and (~failed[strata == k]).any()]
    if not both:
        out["message"] = f"no run holds both a failure and a success {where}: no AUROC within conditions"
        return out
    w = weights[:, idx]
    base = np.asarray([_value(fitted[P.BASELINE].scores[i], at[i]) for i in idx])
    base_draws = S.bootstrap_auroc(base, failed, strata, w)
    for name in fitted:
        within = np.asarray([_value(fitted[name].scores[i], at[i]) for i in idx])
        across = np.asarray([_value(pooled[name].scores[i], at[i]) for i in idx])
        draws = S.bootstrap_auroc(within, failed, strata, w)
        row = {"episodes": int(np.isfinite(within).sum()), "auroc": S.auroc(within, failed, strata),
               "interval": _interval(draws),
               "pooled_auroc": S.auroc(across, failed, folds),
               "pooled_interval": _interval(S.bootstrap_auroc(across, failed, folds, w))}
        if name == P.BASELINE:
            row["verdict"] = "the baseline"
        else:
            difference = _interval(draws - base_draws)
            row["difference"] = row["auroc"] - S.auroc(base, failed, strata)
            row["difference_interval"] = difference
            if not math.isfinite(row["auroc"]):
                row["verdict"] = "no score on both classes within a run"
            else:
                row["verdict"] = BETTER if math.isfinite(difference[0]) and difference[0] > 0 else NOT_BETTER
        out["predictors"][name] = row
    return out


def phase_entries(episode: EpisodeSignals, phase: int) -> int | None:
    """The first step the episode was in `phase` or beyond, None when it never got there."""
    reached = np.flatnonzero(episode.phase >= phase)
    return int(reached[0]) if len(reached) else None


def lead_times(episodes: list[EpisodeSignals], fitted: dict) -> dict:
    """{predictor: flagged share of held-out failures, median lead to the stall step, false-alarm rate on held-out
    successes, the training false-alarm rate} (within conditions' scores and thresholds)."""
    out = {}
    for name, fit in fitted.items():
        fails, oks, leads, flagged_ok = 0, 0, [], 0
        for i, episode in enumerate(episodes):
            score, cut = fit.scores[i], fit.threshold[i]
            if score is None or not np.isfinite(cut):
                continue
            flag = S.first_flag(score, cut)
            if episode.success:
                oks += 1
                flagged_ok += flag is not None
            else:
                fails += 1
                if flag is not None:
                    leads.append(S.stall_step(episode.phase if episode.has_phases else None, episode.steps) - flag)
        trained = fit.training_false_alarm[np.isfinite(fit.training_false_alarm)]
        row = {"failures": fails, "successes": oks, "flagged_failures": len(leads),
               "flagged_share": len(leads) / fails if fails else math.nan,
               "median_lead": float(np.median(leads)) if leads else math.nan,
               "false_alarm": flagged_ok / oks if oks else math.nan,
               "training_false_alarm": float(trained.max()) if len(trained) else math.nan}
        if not (fails and oks):
            row["message"] = (f"too few successful training episodes to calibrate a threshold (at least {S.MIN_CLASS} "
                              f"a fold are needed)" if not np.isfinite(fit.threshold).any() else
                              "no held-out failures and successes both scored")
        out[name] = row
    return out


def evaluate_task(episodes: list[EpisodeSignals], folds: int = 5, resamples: int = S.RESAMPLES, seed: int = 0) -> dict:
    """One task's tables: {"by_step", "by_phase", "lead_time", "predictors", "folds", "episodes", ...}."""
    seeds = [e.seed for e in episodes]
    fold = S.seed_folds(seeds, folds, seed)
    names = [p for p in P.PREDICTORS if P.available(episodes, p)]
    fitted = {p: P.scores(episodes, fold, p, within=True) for p in names}
    pooled = {p: P.scores(episodes, fold, p, within=False) for p in names}
    weights = S.cluster_draws(seeds, resamples, seed)
    by_step = [moment(episodes, [t if t < e.steps else None for e in episodes], fitted, pooled, weights, fold,
                      f"at t = {t}")
               for t in STEPS]
    phases = max((e.phase_names for e in episodes), key=len)
    by_phase = []
    if any(e.has_phases for e in episodes):
        for k, name in enumerate(phases):
            entry = moment(episodes, [phase_entries(e, k) for e in episodes], fitted, pooled, weights,
                           fold, f"on entering {name}")
            by_phase.append({"phase": name, **entry})
    return {"episodes": len(episodes), "failures": sum(not e.success for e in episodes),
            "seeds": len(set(seeds)), "folds": int(fold.max()) + 1 if len(fold) else 0,
            "runs": sorted({e.run for e in episodes}), "predictors": names,
            "missing": [p for p in P.PREDICTORS if p not in names],
            "phases": list(phases) if by_phase else [],
            "by_step": by_step, "by_phase": by_phase,
            "no_phases": None if by_phase else "no phases recorded (e.g. Door, LIBERO): no per-phase AUROC",
            "lead_time": lead_times(episodes, fitted)}

"""Which measure predicts failure over a grid (issue 45 item 3): nuisance reliance against nuisance attention, within
conditions, paired by seed-cluster resamples. Hand-made episodes whose answer is known: a measure that is high exactly
in the failed episodes of each run goes with failure; one drawn independently of success does not."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness.analysis import predictors as P
from harness.analysis import robustness as R


def _rows(reliance_tied: bool, attention_tied: bool, seeds: int = 20, with_reliance: bool = True):
    """Two runs (nominal, one perturbed cell) of `seeds` episodes each; in each run about a third fail. A 'tied'
    measure is 0.2 above its run's level in the failed episodes (plus small noise); an untied one is pure noise."""
    rng = np.random.default_rng(7)
    out = []
    for run, level, base in (("nominal", 0, 0.3), ("texture-5", 5, 0.6)):
        for seed in range(seeds):
            success = bool(rng.random() > (0.25 if level == 0 else 0.45))
            noise = rng.normal(0, 0.02, 2)
            attention = base + (0.0 if success or not attention_tied else 0.2) + (noise[0] if attention_tied else
                                                                                 rng.normal(0, 0.1))
            reliance = base + (0.0 if success or not reliance_tied else 0.2) + (noise[1] if reliance_tied else
                                                                               rng.normal(0, 0.1))
            out.append(R.EpisodeRow(run, "Lift", "nominal" if level == 0 else "texture", level, seed, seed, "ok",
                                    success, attention, 0.5, 0.0, attention,
                                    nuisance_reliance=reliance if with_reliance else math.nan))
    return out


def test_reliance_tied_to_failure_is_named_the_better_predictor():
    (row,) = P.predictor_rows(_rows(reliance_tied=True, attention_tied=False))
    task, map_, episodes, seeds, failures, r_rel, rel_lo, rel_hi, r_att, att_lo, att_hi, diff, lo, hi, verdict = row
    assert (task, map_, episodes, seeds) == ("Lift", "raw", 40, 20) and failures >= R.MIN_CLASS
    assert r_rel < -0.8 and rel_hi < 0  # tied to failure by construction: an interval below 0
    assert att_lo < 0 < att_hi  # independent of success: the interval holds 0
    assert hi < 0 and diff == r_rel - r_att
    assert verdict == ("nuisance reliance is the better predictor of failure (its r is lower), and it predicts failure "
                       "by itself (its own interval lies below 0)")
    (cells,) = P.predictor_table("Lift", [row])  # the table row says the same, every figure in its own column
    assert cells == ("raw map", f"r {r_rel:+.2f} [{rel_lo:+.2f}, {rel_hi:+.2f}]", f"r {r_att:+.2f} [{att_lo:+.2f}, "
                     f"{att_hi:+.2f}]", f"{diff:+.2f} [{lo:+.2f}, {hi:+.2f}]", "-",
                     "nuisance reliance, which predicts failure alone", "40", "20", str(failures))


def test_attention_tied_to_failure_is_named_instead():
    (row,) = P.predictor_rows(_rows(reliance_tied=False, attention_tied=True))
    assert row[12] > 0 and row[14].startswith("nuisance attention (raw map) is the better predictor of failure")
    assert row[10] < 0 and row[14].endswith("it predicts failure by itself (its own interval lies below 0)")


def test_a_better_predictor_whose_own_interval_holds_0_is_not_said_to_predict_failure():
    result = (-0.2, -0.6, 0.2, 0.4, 0.1, 0.7, -0.6, -1.1, -0.2)  # reliance lower, but its own interval holds 0
    assert P.verdict(result, "raw").endswith("it does not predict failure by itself here")
    assert P.verdict((0.3, 0.0, 0.5, -0.4, -0.7, -0.1, 0.7, 0.3, 1.1), "content").startswith(
        "nuisance attention (content-only map) is the better predictor of failure")


def test_two_measures_equally_tied_give_neither_with_the_resolvable_difference():
    (row,) = P.predictor_rows(_rows(reliance_tied=True, attention_tied=True))
    assert row[12] < 0 < row[13]
    assert row[14].startswith("neither is shown to predict failure better")
    assert f"about {(row[13] - row[12]) / 2:.2f}" in row[14]


def test_no_reliance_gives_no_rows_and_no_sentence():
    rows = _rows(reliance_tied=True, attention_tied=False, with_reliance=False)
    assert P.predictor_rows(rows) == [] and P.predictor_table("Lift", []) == []


def test_too_few_failures_gives_no_interval_and_says_so():
    few = [R.EpisodeRow(**{**r.__dict__, "success": True}) if i > 2 else r for i, r in enumerate(_rows(True, False))]
    (row,) = P.predictor_rows(few)
    assert math.isnan(row[12]) and row[14].startswith("too few seeds, successes or failures")


def test_the_association_table_gains_a_reliance_row_with_its_own_words():
    rows = _rows(reliance_tied=True, attention_tied=False)
    association = R.association_rows(rows)
    assert [a[16] for a in association] == ["raw", "reliance"]
    table = R.association_table("Lift", association)
    reliance = [row for row in table if row[0] == "reliance" and row[2] == "episodes"]
    (raw_row,) = [a for a in association if a[16] == "reliance"]
    assert reliance == [("reliance", "nuisance reliance", "episodes", f"{raw_row[2]:+.2f}",
                         f"[{raw_row[5]:+.2f}, {raw_row[6]:+.2f}]", "more goes with failure", "-", str(raw_row[1]),
                         str(raw_row[9]))]


@pytest.mark.slow
def test_the_report_and_eval_md_carry_the_comparison_from_episode_folders(tmp_path):
    """The glue: a nominal and a perturbed run of hand-made episode folders with reliance.jsonl give
    robustness_predictors.csv and the 'which predicts failure' line in the EVAL.md section."""
    from types import SimpleNamespace

    from harness.report import robustness as report
    from tests.analysis.test_robustness_reliance import _episode, _reliance_rows

    records = []
    for run, perturb in (("nominal", None), ("lighting-5", "lighting:5")):
        episodes = [_episode(tmp_path / run / f"ep{seed}", seed, seed % 3 != 0,
                             _reliance_rows(0, {"target": 0.5, "background": 0.5 if seed % 3 == 0 else 0.1}))
                    for seed in range(12)]
        records.append(SimpleNamespace(name=run, manifest={"protocol": {"perturb": perturb, "policy": {}}},
                                       episodes=episodes))
    columns, rows = report.tables(records)["robustness_predictors.csv"]
    assert columns == P.PREDICTOR_COLUMNS and [(r[0], r[1], r[2], r[4]) for r in rows] == [("Lift", "raw", 24, 8)]
    text = report.markdown(records)
    assert "Lift, which predicts failure within conditions (" in text
    assert "| raw map | r -1.00 " in text  # the failed episodes are exactly those with more background reliance

"""Robustness cells get BREAKS / HOLDS / UNDETERMINED, HOLDS by the same equivalence test as compare's HELD, and every
null statement states the smallest drop it could have detected (issue 43 item 3)."""

from __future__ import annotations

import math

import pytest

from harness.analysis.paired import (PairedCounts, decide, detectable_loss, detectable_phrase, equivalent,
                                     difference_interval, mcnemar_exact)
from harness.analysis.robustness import (CellVerdict, EpisodeRow, cell_verdict, paired_rows, success_rows,
                                         verdict_line)


@pytest.mark.parametrize("pairs, alpha, cells, expected", [
    (20, 0.05, 1, 6),     # 2 * 0.5**6 = 0.031 <= 0.05 < 2 * 0.5**5 = 0.0625
    (20, 0.05, 21, 10),   # 21 * 2 * 0.5**10 = 0.041 <= 0.05 < 21 * 2 * 0.5**9 = 0.082: the issue's "about 50 points"
    (20, 0.01, 1, 8),     # 2 * 0.5**8 = 0.0078 <= 0.01 < 2 * 0.5**7 = 0.0156
    (9, 0.05, 21, None),  # 9 pairs can never reach it over 21 cells
    (5, 0.05, 1, None),   # 2 * 0.5**5 = 0.0625 > 0.05: five pairs detect nothing alone
    (0, 0.05, 1, None),
])
def test_detectable_loss_is_the_fewest_lost_pairs_the_exact_test_declares(pairs, alpha, cells, expected):
    assert detectable_loss(pairs, alpha, cells) == expected
    if expected is not None:  # the definition, checked against the test itself
        assert cells * mcnemar_exact(expected, 0) <= alpha < cells * mcnemar_exact(expected - 1, 0)


def test_detectable_phrase_reads_as_the_issue_states_it():
    assert detectable_phrase(20, 0.05, 21) == "no drop of 50 points or more at 20 pairs (Holm over 21 cells)"
    assert detectable_phrase(20, 0.05, 1) == "no drop of 30 points or more at 20 pairs (alpha 0.05)"
    assert detectable_phrase(5, 0.05, 1) == "no drop at all is detectable at 5 pairs (alpha 0.05)"


def _same(n: int) -> PairedCounts:
    return PairedCounts.from_outcomes([True] * n, [True] * n)


def test_holds_and_held_are_one_equivalence_test():
    # compare's HELD (one table alone) and a robustness cell's HOLDS (one cell) agree on every table here
    tables = [_same(20), _same(40), _same(100), PairedCounts.from_outcomes([True] * 40, [True] * 36 + [False] * 4),
              PairedCounts.from_outcomes([True] * 60, [True] * 50 + [False] * 10)]
    for counts in tables:
        held = decide(counts, 0.15, 0.05) == "HELD"
        holds = cell_verdict(counts, mcnemar_exact(counts.baseline_only, counts.candidate_only), 1) == "HOLDS"
        assert held == holds == equivalent(counts, difference_interval(counts, 0.95), 0.15, 0.05), counts
    assert cell_verdict(_same(40), 1.0, 1) == "HOLDS"  # 40 identical pairs rule out a 15-point drop alone
    assert cell_verdict(_same(40), 1.0, 21) == "UNDETERMINED"  # but not with the interval at 1 - 0.05 / 21
    assert cell_verdict(_same(20), 1.0, 1) == "UNDETERMINED"  # 20 pairs never rule out 15 points
    assert cell_verdict(_same(40), 1.0, 1, margin=0.30) == "HOLDS" and cell_verdict(_same(20), 1.0, 1, margin=0.40) == "HOLDS"


def _cell(run, condition, level, outcomes):
    return [EpisodeRow(run, "Lift", condition, level, seed, seed, "ok", ok, 0.8, 0.5, 0.0, 0.8)
            for seed, ok in enumerate(outcomes)]


def test_each_cell_has_a_verdict_and_the_sentence_states_its_power():
    rows = (_cell("nominal", "nominal", 0, [True] * 20) + _cell("texture-5", "texture", 5, [False] * 20)
            + _cell("camera-1", "camera@image_wrist", 1, [True] * 20))
    paired = {p.run: p for p in paired_rows(rows)}
    assert paired["texture-5"].verdict == CellVerdict.BREAKS and paired["camera-1"].verdict == CellVerdict.UNDETERMINED
    assert paired["camera-1"].margin == 0.15 and paired["camera-1"].detectable_drop == pytest.approx(7 / 20)  # 7 lost
    assert paired["camera-1"].drop_upper == pytest.approx(-difference_interval(_same(20), 1 - 0.05 / 2)[0])
    # the task's verdict in one short line; the figures behind it (counts, p, the detectable drop) are the cell's row
    text = verdict_line("Lift", success_rows(rows), list(paired.values()))
    assert text == "Lift: nominal 20/20. Breaks under texture 5. Other cells: 0 HOLD, 1 UNDETERMINED." and len(text.split()) <= 25
    t = paired["texture-5"]
    assert (t.perturbed_successes, t.nominal_successes, t.pairs, t.cells) == (0, 20, 20, 2)
    assert round(100 * t.detectable_drop) == 35 and detectable_phrase(20, 0.05, 2) == \
        "no drop of 35 points or more at 20 pairs (Holm over 2 cells)"
    nothing = _cell("nominal", "nominal", 0, [True] * 20) + _cell("camera-1", "camera@image_wrist", 1, [True] * 20)
    (held,) = paired_rows(nothing, margin=0.40)
    assert verdict_line("Lift", [], [held]) == "Lift: no nominal run to compare with. No cell breaks it. Cells: 1 HOLD, 0 UNDETERMINED."
    assert held.verdict == "HOLDS" and held.margin == 0.40 and round(100 * held.detectable_drop) == 30
    every = _cell("nominal", "nominal", 0, [True] * 20) + _cell("texture-5", "texture", 5, [False] * 20)
    text = verdict_line("Lift", success_rows(every), paired_rows(every))
    assert text == "Lift: nominal 20/20. Breaks under every cell (1)."  # not "0 of the other 0 cells HOLD"
    assert math.isnan(paired_rows(_cell("nominal", "nominal", 0, [True] * 5)
                                  + _cell("c-1", "camera@image_wrist", 1, [True] * 5))[0].detectable_drop)  # 5 pairs: nothing

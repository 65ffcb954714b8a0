"""The regression gate's decision layer on the audit's cases (issue 16), each with a known answer.

1. a task that breaks cannot hide behind one that improves (per-task sequential tests, regress = worse of the
   sequential and the fixed-size verdict); Monte Carlo: power on the swap, family-wise error under no change;
2. errored episodes are not outcomes: left out of n, counted, never HELD/IDENTICAL, ERRORED (exit 3) when an
   arm errored on most of its pairs;
3. a verdict never contradicts its printed interval (SUSPECT, exit 1), and REGRESSED-unreachable is said;
4. one tie rule on both sequential paths; exact McNemar power; HELD's error by exact enumeration.
"""

import itertools

import numpy as np
import pytest
from scipy.stats import binom, binomtest, multinomial

from harness import cli
from harness.analysis.compare import CompareConfig, compare_runs, exit_code
from harness.analysis.outcomes import outcome_verdicts, overall_verdict
from harness.analysis.paired import (
    ErroredPairs,
    PairedCounts,
    decide,
    held_pvalue,
    mcnemar_exact,
    mcnemar_exact_power,
    mcnemar_exact_sample_size,
    mcnemar_sample_size,
    newcombe_paired_interval,
    pairs_for_regressed,
)
from harness.analysis.sequential import (
    SequentialConfig,
    SequentialTest,
    first_decisions,
    log_wealth_paths,
    taskwise_decisions,
)
from harness.run.protocol import EpisodeJob
from harness.gate.regress import gate_on_outcomes, gate_verdict
from harness.verdicts import GateVerdict, gate_exit_code
from tests.analysis.test_compare_outcomes import write_run

ALPHA, MAX_DROP = 0.05, 0.1


# ------------------------------------------------------------------------------ 1. a task cannot hide


def _jobs(tasks, episodes):
    return [EpisodeJob(t, k, k) for t in tasks for k in range(episodes)]


def test_audit_lift_breaks_while_stack_improves_fails_regress_and_compare(tmp_path):
    tasks, seeds = ("Lift", "Stack"), 60
    baseline = {**{("Lift", k): True for k in range(seeds)}, **{("Stack", k): False for k in range(seeds)}}
    candidate = {**{("Lift", k): False for k in range(seeds)}, **{("Stack", k): True for k in range(seeds)}}
    # the defect: one unit per round = mean over tasks is 0 every round, and the averaged stream is HELD
    verdict, used = first_decisions(np.zeros(seeds), SequentialConfig(ALPHA, MAX_DROP))
    assert verdict == "HELD"
    # the fix: Lift's own test (alpha / 2) regresses after a few of its pairs; the gate stops there and fails
    gate = gate_on_outcomes(baseline, candidate, _jobs(tasks, seeds), tasks, ALPHA, MAX_DROP)
    lift = gate.test.tests["Lift"]
    config = SequentialConfig(ALPHA / 2, MAX_DROP)
    expected = int(first_decisions(np.full(seeds, -1.0), config)[1])
    assert lift.verdict == "REGRESSED" and lift.units == expected == gate.rounds < 15
    assert gate.sequential_verdict == "REGRESSED" and gate.verdict == "REGRESSED"
    assert gate_exit_code(gate.verdict) == 1
    # compare on all 60 pairs of each task: Lift REGRESSED (p = 2^-59, Holm x3), Stack IMPROVED -> REGRESSED, exit 1
    base = write_run(tmp_path / "base", {"Lift": [True] * seeds, "Stack": [False] * seeds})
    cand = write_run(tmp_path / "cand", {"Lift": [False] * seeds, "Stack": [True] * seeds}, model="m2")
    result = compare_runs(base, cand)
    blocks = result.outcomes.tasks
    assert blocks["Lift"].verdict == "REGRESSED" and blocks["Stack"].verdict == "IMPROVED"
    pooled = result.outcomes.overall.paired_verdict
    assert pooled == "UNDERPOWERED" and gate_exit_code(pooled) == 0  # the pooled table alone would hide it
    assert result.verdict == "REGRESSED" and exit_code(result) == 1


def test_regress_verdict_is_the_worse_of_sequential_and_fixed_size():
    assert gate_verdict("HELD", "SUSPECT") == "SUSPECT"
    assert gate_verdict("UNDERPOWERED", "REGRESSED") == "REGRESSED"
    assert gate_verdict("REGRESSED", "HELD") == "REGRESSED"
    assert gate_verdict("HELD", "IMPROVED") == "HELD"
    assert gate_verdict("UNDERPOWERED", "IDENTICAL") == "IDENTICAL"  # nothing changed at all
    assert GateVerdict.worst(["IMPROVED", "HELD", "UNDERPOWERED", "SUSPECT", "REGRESSED", "ERRORED"]) == "ERRORED"


def _simulate(rates, pairs, runs, rng, correlation=0.0):
    """[(baseline (runs, pairs) bool, candidate (runs, pairs) bool)] per task (paired Bernoulli, shared draw)."""
    arms = []
    for pb, pc in rates:
        shared, own_b, own_c = rng.random((3, runs, pairs))
        tie = rng.random((runs, pairs)) < correlation
        arms.append((np.where(tie, shared, own_b) < pb, np.where(tie, shared, own_c) < pc))
    return arms


def _gate_monte_carlo(rates, pairs, runs, seed, correlation=0.0):
    """(sequential verdicts (runs,), gate verdicts (runs,)): regress's decision on simulated tasks."""
    arms = _simulate(rates, pairs, runs, np.random.default_rng(seed), correlation)
    y = np.stack([c.astype(np.int8) - b.astype(np.int8) for b, c in arms])  # (tasks, runs, pairs)
    sequential, stop = taskwise_decisions(y, SequentialConfig(ALPHA, MAX_DROP))
    config = CompareConfig(max_drop=MAX_DROP, alpha=ALPHA)
    gate = []
    for r in range(runs):
        if sequential[r] == "REGRESSED":  # the worse of the two is REGRESSED whatever compare says
            gate.append("REGRESSED")
            continue
        tables = {f"task{t}": PairedCounts.from_outcomes(list(b[r, : stop[r]]), list(c[r, : stop[r]]))
                  for t, (b, c) in enumerate(arms)}
        gate.append(gate_verdict(sequential[r], overall_verdict(outcome_verdicts(tables, config, project=False))))
    return sequential, np.array(gate, dtype=object)


def test_monte_carlo_a_broken_task_with_an_improved_one_fails_the_gate():
    # the audit's simulation: Lift 0.8 -> 0.3, Stack 0.3 -> 0.8, 60 seeds each (the mean over tasks exited 0 in
    # 397/400 runs); now the gate fails in every one of 400 runs (Lift's own test: REGRESSED in 99.5%)
    sequential, gate = _gate_monte_carlo([(0.8, 0.3), (0.3, 0.8)], pairs=60, runs=400, seed=0)
    codes = np.array([gate_exit_code(v) for v in gate])
    print(f"swap: sequential REGRESSED {np.mean(sequential == 'REGRESSED'):.4f}, gate fails {np.mean(codes != 0):.4f}")
    assert np.mean(sequential == "REGRESSED") >= 0.98
    assert np.mean(codes != 0) >= 0.99


@pytest.mark.slow
@pytest.mark.parametrize("rates, correlation", [([(0.8, 0.8), (0.5, 0.5)], 0.5),
                                                ([(0.5, 0.5), (0.5, 0.5), (0.9, 0.9)], 0.0)])
def test_monte_carlo_no_change_keeps_the_family_wise_error(rates, correlation):
    # measured (300 runs of 100 rounds): sequential false REGRESSED 0% and 1.7%, gate failing (REGRESSED or
    # SUSPECT from either part) 1.3% and 3.7%; both must stay <= alpha
    sequential, gate = _gate_monte_carlo(rates, pairs=100, runs=300, seed=1, correlation=correlation)
    codes = np.array([gate_exit_code(v) for v in gate])
    false_regressed, fails = np.mean(sequential == "REGRESSED"), np.mean(codes != 0)
    print(f"no change {rates}: sequential false REGRESSED {false_regressed:.4f}, gate fails {fails:.4f}")
    assert false_regressed <= ALPHA and fails <= ALPHA


# ------------------------------------------------------------------------------ 2. errored episodes


def test_a_candidate_whose_every_episode_errored_is_errored_exit_3(tmp_path, capsys):
    base = write_run(tmp_path / "base", {"Lift": [True, True]})
    cand = write_run(tmp_path / "cand", {"Lift": [None, None]}, model="m2")
    result = compare_runs(base, cand)
    lift = result.outcomes.tasks["Lift"]
    assert lift.pairs == 0 and lift.errored_pairs == 2 and lift.candidate.errored == 2
    assert lift.difference is None and result.verdict == "ERRORED" and exit_code(result) == 3
    assert exit_code(result, "regressed") == 3  # no --fail-on lets it pass
    assert cli.main(["compare", str(base), str(cand), "--no-frames"]) == 3
    out = capsys.readouterr().out
    assert "the candidate errored on 2 of 2 paired episodes in Lift" in out and "Exit code 3" in out


def test_both_arms_errored_is_errored_and_says_the_baseline_cannot_pass(tmp_path):
    base = write_run(tmp_path / "base", {"Lift": [None] * 40})
    cand = write_run(tmp_path / "cand", {"Lift": [None] * 40}, model="m2")
    result = compare_runs(base, cand)
    assert result.verdict == "ERRORED" and exit_code(result) == 3
    notes = " ".join(result.outcomes.notes)
    assert "the baseline errored on 40 of 40" in notes and "the baseline cannot serve as the reference" in notes


def test_errored_pairs_are_left_out_of_n_and_never_give_held_or_identical(tmp_path, capsys):
    # 80 concordant successes would be HELD; two errored candidate episodes make it UNDERPOWERED at best
    base = write_run(tmp_path / "base", {"Lift": [True] * 82})
    cand = write_run(tmp_path / "cand", {"Lift": [True] * 80 + [None, None]}, model="m2")
    result = compare_runs(base, cand)
    lift = result.outcomes.tasks["Lift"]
    assert lift.pairs == 80 and lift.errored_pairs == 2 and lift.table.both == 80
    assert lift.baseline.n == lift.candidate.n == 80 and lift.candidate.errored == 2
    assert decide(PairedCounts(both=80), MAX_DROP, ALPHA) == "HELD"
    assert lift.verdict == "UNDERPOWERED" and result.verdict == "UNDERPOWERED" and exit_code(result) == 0
    assert decide(PairedCounts(both=80), MAX_DROP, ALPHA, errored=ErroredPairs(0, 2, 2)) == "UNDERPOWERED"
    cli.main(["compare", str(base), str(cand), "--no-frames"])
    out = capsys.readouterr().out
    assert "| Lift | 80 (+2 errored) | 80/80 = 1.00 [0.95, 1.00] | 80/80 = 1.00 [0.95, 1.00] (2 errored) |" in out
    assert "2 errored pair(s) in Lift left out of n = 80" in out


def test_n_counts_pairs_with_an_outcome_like_the_run_store():
    from types import SimpleNamespace

    from harness.run.store import statistics

    rows = [SimpleNamespace(task="Lift", status=s, success=v, lost_infrastructure=False)  # episode failures, not lost jobs
            for s, v in [("ok", True)] * 8 + [("failed", None)] * 2]
    store = statistics(rows, ["Lift"])["tasks"]["Lift"]
    errored = ErroredPairs.from_statuses([True] * 10, [r.status == "ok" for r in rows])
    table = PairedCounts.from_outcomes([True] * 8, [bool(r.success) for r in rows if r.status == "ok"])
    block = outcome_verdicts({"Lift": table}, CompareConfig(), {"Lift": errored}).tasks["Lift"]
    assert store["n"] == block.candidate.n == 8 and store["failed"] == block.candidate.errored == 2


# ------------------------------------------------------------------------------ 3. the interval and the verdict


def test_audit_stack_drop_shown_by_the_interval_is_suspect_not_held(tmp_path, capsys):
    # Stack 4/5 -> 0/5 beside a Lift that holds: -0.80 with an interval below 0, exact p = 0.125 (unreachable
    # REGRESSED at 5 pairs). Before: overall HELD, exit 0. Now: Stack SUSPECT, overall SUSPECT, exit 1.
    base = write_run(tmp_path / "base", {"Lift": [True] * 80, "Stack": [True] * 4 + [False]})  # Stack: 5 finished
    cand = write_run(tmp_path / "cand", {"Lift": [True] * 80, "Stack": [False] * 5}, model="m2")
    stack_alone = PairedCounts(baseline_only=4, neither=1)
    low, high = newcombe_paired_interval(0, 0, 4, 1)
    assert (round(low, 2), round(high, 2)) == (-0.96, -0.19) and mcnemar_exact(4, 0) == pytest.approx(0.125)
    assert decide(stack_alone, MAX_DROP, ALPHA) == "SUSPECT"
    result = compare_runs(base, cand)
    stack = result.outcomes.tasks["Stack"]
    assert stack.difference_ci[1] < 0 and stack.mcnemar_p_holm > ALPHA
    assert stack.verdict == "SUSPECT" and result.outcomes.tasks["Lift"].verdict == "HELD"
    assert result.verdict == "SUSPECT" and exit_code(result) == 1 and exit_code(result, "regressed") == 0
    assert cli.main(["compare", str(base), str(cand), "--no-frames"]) == 1
    assert "**SUSPECT**" in capsys.readouterr().out


def test_regressed_unreachable_with_few_pairs_is_said(tmp_path):
    base = write_run(tmp_path / "base", {"Lift": [True] * 5, "Stack": [True] * 5})
    cand = write_run(tmp_path / "cand", {"Lift": [True] * 5, "Stack": [False] * 5}, model="m2")
    result = compare_runs(base, cand)
    stack = result.outcomes.tasks["Stack"]
    # smallest exact p with 5 pairs: 2 / 2^5 = 0.0625; Holm factor 3 (Lift, Stack, pooled): 7 pairs needed
    assert stack.holm_factor == 3 and not stack.regressed_reachable and stack.pairs_for_regressed == 7
    assert pairs_for_regressed(0.05) == 6 and pairs_for_regressed(0.05, 3) == 7
    assert stack.verdict == "SUSPECT" and exit_code(result) == 1
    assert ("REGRESSED is unreachable with 5 pairs in Stack: the smallest exact McNemar p is 0.0625 (x Holm factor 3 "
            "= 0.188) > alpha 0.05; at least 7 pairs are needed.") in result.outcomes.notes


def test_exit_codes_of_every_verdict_and_fail_on_level():
    table = {"IDENTICAL": (0, 0, 0, 0), "IMPROVED": (0, 0, 0, 1), "HELD": (0, 0, 0, 1),
             "UNDERPOWERED": (0, 0, 1, 1), "SUSPECT": (0, 1, 1, 1), "REGRESSED": (1, 1, 1, 1), "ERRORED": (3, 3, 3, 3)}
    for verdict, codes in table.items():
        assert tuple(gate_exit_code(verdict, f) for f in ("regressed", "suspect", "underpowered", "changed")) == codes
    with pytest.raises(ValueError):
        gate_exit_code("HELD", "nothing")


def test_an_identical_task_row_says_identical(tmp_path, monkeypatch):
    from harness.analysis import compare as compare_module
    from harness.report.compare_md import markdown_summary

    base = write_run(tmp_path / "base", {"Lift": [True, False]})
    result = compare_runs(base, base)
    assert result.outcomes.tasks["Lift"].verdict == "UNDERPOWERED"  # hand-made runs have no arrays
    original = compare_module._compare_pair  # every array equal, as the real check finds for a run with itself
    monkeypatch.setattr(compare_module, "_compare_pair",
                        lambda *a, **k: {**original(*a, **k), "identical": True, "difference": None})
    result = compare_runs(base, base)
    lift = result.outcomes.tasks["Lift"]
    assert result.verdict == "IDENTICAL" and lift.verdict == "IDENTICAL"
    assert lift.paired_verdict == "UNDERPOWERED"
    assert lift.notes and result.outcomes.notes == ()  # "REGRESSED is unreachable" is moot when identical
    text = markdown_summary(result, 0)
    assert "**IDENTICAL**" in text and "UNDERPOWERED" not in text
    assert "difference = candidate - baseline" in text


# ------------------------------------------------------------------------------ 4. ties, power, HELD's error


def test_one_tie_rule_on_both_sequential_paths():
    # all-success candidate, max_drop 0.02: IMPROVED and HELD both cross at unit 8
    config = SequentialConfig(alpha=ALPHA, max_drop=0.02)
    paths = log_wealth_paths(np.ones(20), config)
    level = np.log(config.threshold)
    assert np.argmax(paths["improvement"] >= level) == np.argmax(paths["held"] >= level) == 7
    verdict, used = first_decisions(np.ones(20), config)
    test = SequentialTest(config)
    while test.add(1.0) is None:
        pass
    assert (str(verdict), int(used)) == (test.verdict, test.units) == ("IMPROVED", 8)


def test_exact_mcnemar_power_by_enumeration_and_the_exact_sample_sizes():
    # power with n = 12 by brute force over every (baseline_only, candidate_only, concordant) table
    pb, pc, n = 0.4, 0.1, 12
    brute = sum(multinomial.pmf([b, c, n - b - c], n, [pb, pc, 1 - pb - pc])
                for b, c in itertools.product(range(n + 1), repeat=2) if b + c <= n
                and b + c > 0 and binomtest(c, b + c, 0.5).pvalue <= ALPHA)
    assert mcnemar_exact_power(n, pb, pc, ALPHA) == pytest.approx(brute, rel=1e-10)
    # Connor's asymptotic n (42 and 67 pairs, tests/analysis/test_paired_statistics.py) against the exact test's
    assert mcnemar_sample_size(0.4, 0.1, ALPHA, 0.8) == 42 and mcnemar_exact_sample_size(0.4, 0.1, ALPHA, 0.8) == 46
    assert mcnemar_sample_size(0.4, 0.1, ALPHA, 0.95) == 67 and mcnemar_exact_sample_size(0.4, 0.1, ALPHA, 0.95) == 71
    assert mcnemar_exact_power(46, 0.4, 0.1) >= 0.8 > mcnemar_exact_power(45, 0.4, 0.1)
    assert mcnemar_exact_sample_size(0.2, 0.2) is None


def _wilson(k, n, confidence):
    from scipy.stats import norm

    z = norm.ppf(1 - (1 - confidence) / 2)
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def _newcombe(both, first, second, neither, confidence):
    """Vectorised newcombe_paired_interval (cross-checked against it below)."""
    n = both + first + second + neither
    p1, p2 = (both + first) / n, (both + second) / n
    l1, u1 = _wilson(both + first, n, confidence)
    l2, u2 = _wilson(both + second, n, confidence)
    margins = (both + first) * (second + neither) * (both + second) * (first + neither)
    cross = both * neither - first * second
    root = np.sqrt(np.maximum(margins, 1))
    phi = np.where(margins == 0, 0.0, np.where(cross > 0, np.maximum(cross - n / 2, 0) / root, cross / root))
    d = (first - second) / n
    low = d - np.sqrt(np.maximum((p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2, 0))
    high = d + np.sqrt(np.maximum((u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2, 0))
    return np.maximum(low, -1), np.minimum(high, 1)


def _verdicts(n):
    """Every 2x2 table of n pairs (k, 4) and its one-task verdict (k,) by the rules of `decide`."""
    t = np.array([(a, b, c, n - a - b - c)
                  for a in range(n + 1) for b in range(n + 1 - a) for c in range(n + 1 - a - b)])
    both, b, c, neither = t.T.astype(float)
    low, high = _newcombe(both, c, b, neither, 1 - ALPHA)
    d = t[:, 1] + t[:, 2]
    p = np.where(d == 0, 1.0, np.minimum(1.0, 2 * binom.cdf(np.minimum(t[:, 1], t[:, 2]), d, 0.5)))
    significant = p <= ALPHA
    verdict = np.full(len(t), "UNDERPOWERED", dtype=object)
    candidates = np.flatnonzero((low >= -MAX_DROP) & (high >= 0) & ~significant)  # HELD if the exact test agrees
    held_p = {bc: held_pvalue(*bc, n, MAX_DROP) for bc in {(int(t[i, 1]), int(t[i, 2])) for i in candidates}}
    verdict[[i for i in candidates if held_p[(int(t[i, 1]), int(t[i, 2]))] <= ALPHA / 2]] = "HELD"
    verdict[high < 0] = "SUSPECT"
    verdict[significant & (t[:, 2] < t[:, 1])] = "REGRESSED"
    verdict[significant & (t[:, 2] > t[:, 1])] = "IMPROVED"
    return t, verdict, low


def test_held_error_by_exact_enumeration_stays_under_nominal():
    # null configurations with true difference exactly -max_drop: p_b = p_c + 0.1, the concordant mass split
    # f : 1 - f between both and neither. HELD's nominal error is alpha / 2 = 2.5% (one side of a 95% interval).
    # Measured over this grid: the new rule <= 1.76%; Newcombe's lower limit alone reached 8.96% (n = 20,
    # p_c = 0, f = 0.5) and 4.24% at n = 30.
    rng = np.random.default_rng(0)
    worst_new, worst_newcombe = 0.0, 0.0
    for n in (10, 20, 30, 50, 80):
        t, verdict, low = _verdicts(n)
        for i in rng.choice(len(t), 40, replace=False):  # the vectorised rules are the real ones
            assert decide(PairedCounts(*t[i]), MAX_DROP, ALPHA) == verdict[i]
        passes = np.isin(verdict, ["HELD", "IMPROVED"])
        newcombe_only = (low >= -MAX_DROP) & ~np.isin(verdict, ["REGRESSED"])
        for pc, f in itertools.product((0.0, 0.05, 0.1, 0.2, 0.4), (0.1, 0.5)):
            pb = pc + MAX_DROP
            rest = 1 - pb - pc
            pmf = multinomial.pmf(t, n, [rest * f, pb, pc, rest * (1 - f)])
            worst_new = max(worst_new, pmf[passes].sum())
            worst_newcombe = max(worst_newcombe, pmf[newcombe_only].sum())
    print(f"HELD error: new rule {worst_new:.4f}, Newcombe's limit alone {worst_newcombe:.4f} (nominal {ALPHA / 2})")
    assert worst_new <= ALPHA / 2
    assert worst_newcombe == pytest.approx(0.0896, abs=5e-4)  # the excess the audit reported, now closed


def test_regress_on_an_all_errored_candidate_is_errored_and_stops_once_more_than_half_errored():
    from harness.gate.regress import _check_baseline, errored_tasks

    tasks, seeds = ("Lift", "Stack"), 10
    jobs = _jobs(tasks, seeds)
    baseline = {(t, k): True for t in tasks for k in range(seeds)}
    candidate = {**{("Lift", k): True for k in range(seeds)}, **{("Stack", k): None for k in range(seeds)}}
    gate = gate_on_outcomes(baseline, candidate, jobs, tasks, ALPHA, MAX_DROP)
    assert gate.test.errored == {"Lift": 0, "Stack": 10} and gate.test.tests["Stack"].units == 0
    assert gate.compare_verdict == "ERRORED" and gate.verdict == "ERRORED"
    assert gate_exit_code(gate.verdict) == 3 and gate_exit_code(gate.verdict, "regressed") == 3
    # the executor stops once the candidate errored on more than half of a task's pairs (5 of 10 is not more)
    partial = {("Stack", k): None for k in range(5)}
    assert errored_tasks(baseline, partial, jobs) == []
    assert errored_tasks(baseline, {**partial, ("Stack", 5): None}, jobs) == ["Stack"]
    # a baseline that errored on most of a task's episodes is refused before anything runs (exit 2)
    broken = {**baseline, **{("Lift", k): None for k in range(6)}}
    with pytest.raises(ValueError, match="errored on 6 of 10 episodes of Lift"):
        _check_baseline(broken, jobs, "base")
    _check_baseline({**baseline, **{("Lift", k): None for k in range(5)}}, jobs, "base")  # half: allowed


def test_regress_never_exits_0_where_compare_on_the_same_pairs_does_not():
    rng = np.random.default_rng(5)
    tasks = ("Lift", "Stack")
    for _ in range(100):
        seeds = int(rng.integers(3, 40))
        rates = rng.random((2, 2))
        baseline = {(t, k): bool(rng.random() < rates[i, 0]) for i, t in enumerate(tasks) for k in range(seeds)}
        candidate = {(t, k): (None if rng.random() < 0.05 else bool(rng.random() < rates[i, 1]))
                     for i, t in enumerate(tasks) for k in range(seeds)}
        gate = gate_on_outcomes(baseline, candidate, _jobs(tasks, seeds), tasks, ALPHA, MAX_DROP)
        for fail_on in ("regressed", "suspect", "underpowered"):
            if gate_exit_code(gate.compare_verdict, fail_on) != 0:
                assert gate_exit_code(gate.verdict, fail_on) != 0, (gate.verdict, gate.compare_verdict)

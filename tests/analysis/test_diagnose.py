"""`octo-harness diagnose` (issue 74 items 2 and 3): the statistics on synthetic data with known answers (AUROC of a
perfect and of a random score, the seed-cluster interval, seed-disjoint folds, the threshold at 5% false alarms, the
stall step, robust z-scores), the whole evaluation on hand-made episodes (a predictor fed the labels scores 1.0, one
fed noise or only the condition is not better than time and phase within conditions), and the command end to end on
two real runs of the tiny fixture (which never succeeds: the one line for too few successes, and failures.csv)."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from harness.analysis.diagnose import stats as S
from harness.analysis.diagnose.evaluate import BETTER, NOT_BETTER, evaluate_task
from harness.analysis.diagnose.failures import failure_rows
from harness.analysis.diagnose.signals import SIGNALS, EpisodeSignals, held, window_mean

# ------------------------------------------------------------------------------------------- statistics


def test_auroc_of_a_perfect_a_reversed_and_a_tied_score():
    failed = np.array([1, 1, 0, 0, 0], bool)
    assert S.auroc([0.9, 0.8, 0.1, 0.2, 0.3], failed) == 1.0
    assert S.auroc([0.1, 0.2, 0.9, 0.8, 0.7], failed) == 0.0
    assert S.auroc(np.ones(5), failed) == 0.5
    assert math.isnan(S.auroc([1.0, 2.0], [True, True]))  # one class: no pair
    # within strata: a score that only tells the strata apart is 0.5 there, and perfect pooled
    strata = np.array([0, 0, 0, 1, 1, 1])
    failed = np.array([1, 0, 0, 1, 1, 0], bool)
    by_stratum = np.array([0.0, 0, 0, 1, 1, 1])
    assert S.auroc(by_stratum, failed, strata) == 0.5
    assert S.auroc(by_stratum, failed) == pytest.approx(6 / 9)  # pooled: (1 + 2.5 + 2.5) of 9 pairs


def test_a_random_score_has_an_interval_holding_half_and_a_perfect_one_sits_at_one():
    rng = np.random.default_rng(0)
    seeds = np.repeat(np.arange(40), 3)  # 3 conditions a seed
    failed = rng.random(len(seeds)) < 0.4
    weights = S.cluster_draws(seeds, 1000, seed=1)
    assert weights.shape == (1000, 120) and np.all(weights[:, 0] == weights[:, 1])  # a seed's episodes go together
    low, high = S.percentile_interval(S.bootstrap_auroc(rng.normal(size=len(seeds)), failed, np.zeros(120), weights))
    assert low < 0.5 < high
    perfect = S.bootstrap_auroc(failed.astype(float), failed, np.zeros(120), weights)
    assert S.percentile_interval(perfect) == (1.0, 1.0)
    assert all(math.isnan(x) for x in S.percentile_interval(np.full(10, np.nan)))


def test_folds_never_split_a_seed():
    seeds = np.repeat(np.arange(23), 4)
    folds = S.seed_folds(seeds, 5, seed=3)
    assert set(folds) == set(range(5))
    for seed in np.unique(seeds):
        assert len(set(folds[seeds == seed])) == 1
    assert set(S.seed_folds([7, 7, 8], 5)) <= {0, 1}  # fewer seeds than folds: one fold a seed


def test_the_threshold_flags_at_most_five_percent_of_the_training_successes():
    rng = np.random.default_rng(2)
    for n in (1, 7, 20, 41, 200):
        peaks = rng.normal(size=n)
        cut = S.calibrate(peaks)
        assert np.mean(peaks > cut) <= S.FALSE_ALARM
    assert S.calibrate([]) == math.inf
    assert S.first_flag([0.1, 0.5, 0.9, 0.2], 0.4) == 1 and S.first_flag([0.1], 0.4) is None


def test_the_stall_step_is_the_first_step_of_the_furthest_phase():
    assert S.stall_step([0, 0, 1, 1, 2, 2, 1, 1]) == 4  # reached phase 2 at step 4, fell back after
    assert S.stall_step([0, 0, 0]) == 0
    assert S.stall_step(None, 100) == 90  # no phases: the last tenth
    assert S.stall_step([-1, -1, -1, -1], 40) == 36


def test_robust_z_scores():
    reference = [1.0, 2.0, 3.0, 4.0, 100.0]  # median 3, MAD 1: the outlier moves neither
    assert S.robust_z(3.0, reference) == 0.0
    assert S.robust_z(6.0, reference) == pytest.approx(3 / S.MAD_SCALE)
    assert math.isnan(S.robust_z(1.0, [1.0, 2.0]))  # fewer than 3
    assert math.isnan(S.robust_z(1.0, [2.0, 2.0, 2.0]))  # no spread


def test_the_logistic_regression_separates_and_is_regularised():
    rng = np.random.default_rng(4)
    x = rng.normal(size=(200, 3))
    y = (x[:, 0] > 0).astype(float)
    model = S.Logistic(1.0).fit(x, y)
    assert S.auroc(model.score(x), y.astype(bool)) > 0.99 and abs(model.beta[1]) > 5 * abs(model.beta[2])
    assert abs(S.Logistic(1e4).fit(x, y).beta[1]) < abs(model.beta[1])  # a stronger penalty shrinks it


def test_signals_are_held_from_their_last_recorded_step():
    np.testing.assert_array_equal(held(5, [1, 3], np.array([10.0, 30.0])), [np.nan, 10, 10, 30, 30])
    np.testing.assert_allclose(window_mean(np.array([1.0, np.nan, 3.0, 5.0]), 2), [1, 1, 3, 4])


# ------------------------------------------------------------------------------------------- the evaluation


def episodes(kind: str, seeds: int = 30, rng=None) -> list[EpisodeSignals]:
    """Three conditions (runs) of `seeds` seeds, failure rates 0.2, 0.5, 0.8; failures reach phase 1 at most and
    run to 120 steps, successes end at 60-119. Readout features: the label (`labels`), noise, or the condition."""
    rng = rng or np.random.default_rng(0)
    out = []
    for c, rate in enumerate((0.2, 0.5, 0.8)):
        for s in range(seeds):
            fail = bool(rng.random() < rate)
            n = 120 if fail else int(rng.integers(60, 120))
            phase = np.minimum(np.arange(n) * 3 // n, 2) if not fail else np.minimum(np.arange(n) * 3 // (2 * n), 1)
            features = {"labels": np.full((n, 4), float(fail)) + 0.01 * rng.normal(size=(n, 4)),
                        "noise": rng.normal(size=(n, 4)),
                        "condition": np.full((n, 4), float(c)) + 1e-3 * rng.normal(size=(n, 4))}[kind]
            signals = {k: rng.normal(size=n) for k in SIGNALS}
            out.append(EpisodeSignals(f"run{c}", "Lift", f"cond{c}", s, s, not fail, n, ("approach", "grasp", "lift"),
                                      phase, signals, features.astype(np.float32), "action consistent"))
    return out


@pytest.fixture(scope="module")
def evaluated():
    return {kind: evaluate_task(episodes(kind), resamples=300) for kind in ("labels", "noise", "condition")}


def test_a_probe_fed_the_labels_scores_one(evaluated):
    result = evaluated["labels"]
    at10 = result["by_step"][0]
    assert at10["where"] == "at t = 10" and at10["failures"] + at10["successes"] == 90
    probe = at10["predictors"]["readout probe"]
    assert probe["auroc"] == 1.0 and probe["verdict"] == BETTER
    lead = result["lead_time"]["readout probe"]
    assert lead["flagged_share"] == 1.0 and lead["median_lead"] > 0 and lead["training_false_alarm"] <= S.FALSE_ALARM
    at100 = result["by_step"][3]
    assert at100["successes"] < at10["successes"]  # successes that ended before t = 100 are not counted there


def test_noise_and_the_condition_alone_are_not_better_than_time_and_phase_within_conditions(evaluated):
    for kind in ("noise", "condition"):
        for cell in evaluated[kind]["by_step"][:3]:
            probe = cell["predictors"]["readout probe"]
            assert probe["interval"][0] < 0.5 < probe["interval"][1], (kind, cell["where"], probe)
            assert probe["verdict"] == NOT_BETTER, (kind, cell["where"])
    pooled = evaluated["condition"]["by_step"][0]["predictors"]["readout probe"]
    assert pooled["pooled_auroc"] > 0.7  # across conditions the condition predicts failure: why it is not the result


def test_too_few_of_a_class_is_a_line_not_a_number():
    few = [e for e in episodes("noise") if not e.success or e.seed < 2]
    cell = evaluate_task(few, resamples=100)["by_step"][0]
    assert cell["predictors"] == {} and cell["message"].startswith("too few successes at t = 10")
    for episode in few:  # no readout features recorded: the probe is left out and named
        episode.features = None
    assert evaluate_task(few, resamples=100)["missing"] == ["readout probe"]


def test_a_failure_row_names_the_stall_and_the_signals_furthest_from_the_successes():
    made = episodes("noise", seeds=12)
    failed = next(e for e in made if not e.success)
    failed.signals["nuisance"][failed.phase == failed.phase.max()] = 50.0  # far from every success
    rows = failure_rows(made)
    row = next(r for r in rows if (r["run"], r["seed"]) == (failed.run, failed.seed))
    assert row["stall_step"] == int(np.flatnonzero(failed.phase == failed.phase.max())[0])
    assert row["furthest_phase"] == "grasp" and row["stall_basis"] == "phases" and float(row["passed_median"]) > 0
    assert row["furthest"].startswith("nuisance +") and float(row["z_nuisance"]) > 10
    assert row["preflight"] == "action consistent" and len(rows) == sum(not e.success for e in made)


# ------------------------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def runs(fixtures_dir, tmp_path_factory):
    """Two short runs of the tiny fixture on Lift with both failure probes (one loaded model)."""
    from harness.octo import load_pretrained
    from harness.outputs.writers import OutputOptions
    from harness.policy import PolicyConfig
    from harness.run import Protocol, execute

    model = load_pretrained(str(fixtures_dir / "tiny"))
    out = tmp_path_factory.mktemp("diagnose")
    policy = PolicyConfig(readout_features_every=1, action_consistency=True)
    for name, seed in (("first", 0), ("second", 10)):
        protocol = Protocol(model=model.source, tasks=("Lift",), episodes=2, max_steps=6, seed=seed, policy=policy,
                            outputs=OutputOptions(png_every=0, video=False))
        execute(protocol, out, name, model=model, progress=False, preflight="off")
    return out


@pytest.mark.slow
def test_diagnose_on_real_runs_writes_its_files_and_says_too_few_successes(runs, capsys):
    from harness import cli

    out = runs / "diagnosis"
    code = cli.main(["diagnose", str(runs / "first"), str(runs / "second"), "--out", str(out), "--resamples", "200"])
    printed = capsys.readouterr().out.splitlines()
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["diagnose.json", "diagnose.md", "failures.csv"]
    (line,) = [p for p in printed if p.startswith("Lift: too few successes")]
    assert "(0 successes, 4 failures; at least 5 of each are needed)" in line
    data = json.loads((out / "diagnose.json").read_text())
    assert data["runs"] == ["first", "second"] and data["tasks"]["Lift"]["message"] == line
    rows = list(csv.DictReader((out / "failures.csv").open()))
    assert len(rows) == 4 and {r["run"] for r in rows} == {"first", "second"}
    assert {r["seed"] for r in rows} == {"0", "1", "10", "11"} and all(r["condition"] == "nominal" for r in rows)
    assert all(r["stall_basis"] == "phases" and r["furthest_phase"] for r in rows)
    assert all(r["preflight"] == "not run" and r["furthest"].startswith("no z-score") for r in rows)
    assert "## Why each failed episode failed" in (out / "diagnose.md").read_text()
    # the signals were read: features and consistency at every step
    from harness.analysis.diagnose.signals import load

    found, _, _ = load([runs / "first"])
    assert found[0].features is not None and found[0].features.shape[0] == 6
    assert np.isfinite(found[0].signals["consistency"][1:]).all() and np.isfinite(found[0].signals["nuisance"]).all()


@pytest.mark.slow
def test_the_eval_md_section_is_written_from_real_runs_and_rendered_from_its_figures_file(runs, tmp_path, capsys):
    from harness.report import early_warning, figures_file

    eval_md = tmp_path / "EVAL.md"
    eval_md.write_text("# a model: evaluation\n\n## Other\n\nKept.\n")
    code = early_warning.main([str(runs / "first"), str(runs / "second"), "--eval-md", str(eval_md),
                               "--resamples", "200"])
    assert code == 0, capsys.readouterr().err
    text = eval_md.read_text()
    assert "## Other\n\nKept." in text and text.count("## Failure early warning") == 1
    doc = figures_file.read(tmp_path / "figures" / "failure-early-warning.json")
    assert figures_file.render(doc) in text and "--resamples 200" in doc["provenance"]
    assert "Lift: too few successes to predict failure (0 successes, 4 failures" in text
    assert "| approach | 4 |" in text or "Where Lift's failed episodes stalled:" in text
    assert "interim" not in text  # both runs finished


@pytest.mark.slow
def test_kept_runs_restore_to_what_diagnose_and_a_resume_read(runs, fixtures_dir, tmp_path):
    """scripts/keep_grid_runs.py (a grid longer than one machine's life, issue 74): the kept archive restores to runs
    whose signals diagnose reads exactly as from the originals, that a resume of the same protocol
    finds finished, and that a second keep leaves byte for byte; a run the grid holds is never overwritten."""
    import importlib.util
    from pathlib import Path

    from harness.analysis.diagnose.signals import load
    from harness.analysis.runs import load_run
    from harness.outputs.writers import OutputOptions
    from harness.policy import PolicyConfig
    from harness.run import Protocol, execute

    path = Path(__file__).resolve().parents[2] / "scripts/keep_grid_runs.py"
    spec = importlib.util.spec_from_file_location("keep_grid_runs", path)
    K = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(K)
    grid = tmp_path / "grid"
    grid.mkdir()
    for name in ("first", "second"):
        (grid / name).symlink_to(runs / name, target_is_directory=True)
    kept = tmp_path / "kept"
    assert K.keep(grid, kept) == ["first", "second"]
    archive = (kept / "first.tar.xz").read_bytes()
    assert K.keep(grid, kept) == [] and (kept / "first.tar.xz").read_bytes() == archive
    assert json.loads((kept / "index.json").read_text()) == {"first": 2, "second": 2}
    restored = tmp_path / "restored"
    assert K.restore(kept, restored) == ["first", "second"] and K.restore(kept, restored) == []
    assert not list(restored.rglob("metrics.jsonl")) and list(runs.rglob("metrics.jsonl"))
    with np.load(restored / "first/Lift/episode_0/attention.npz") as z:
        assert "readout_attention" not in z.files and z["measures/layer/entropy"].shape == (6, 1)
    before, _, _ = load([runs / "first", runs / "second"])
    after, _, _ = load([restored / "first", restored / "second"])
    assert [(e.run, e.seed, e.success, e.steps) for e in after] == [(e.run, e.seed, e.success, e.steps) for e in before]
    for a, b in zip(before, after):
        assert np.array_equal(a.phase, b.phase) and np.array_equal(a.features, b.features, equal_nan=True)
        for name in ("consistency", "entropy", "nuisance", "target", "gripper"):
            assert np.array_equal(a.signals[name], b.signals[name], equal_nan=True), name
    assert load_run(restored / "first").status == "complete"
    protocol = Protocol(model=str(fixtures_dir / "tiny"), tasks=("Lift",), episodes=2, max_steps=6, seed=0,
                        policy=PolicyConfig(readout_features_every=1, action_consistency=True),
                        outputs=OutputOptions(png_every=0, video=False))
    summary = execute(protocol, restored, "first", model=None, progress=False, preflight="off")
    assert summary.skipped == 2 and len(summary.rows) == 2
    (kept / "second.tar.xz").write_bytes(archive[: len(archive) // 2])  # a cut archive: one line, nothing half-restored
    with pytest.raises(SystemExit, match="second.tar.xz is damaged"):
        K.restore(kept, tmp_path / "again")
    assert [p.name for p in (tmp_path / "again").iterdir()] == ["first"]


def test_the_guides_example_on_the_committed_baseline_gives_the_row_it_quotes(tmp_path, capsys):
    """docs/diagnose.md opens with diagnose on results/baselines/reference-lift and quotes its one failure's row."""
    from pathlib import Path

    from harness import cli

    repo = Path(__file__).resolve().parents[2]
    assert cli.main(["diagnose", str(repo / "results/baselines/reference-lift"), "--out", str(tmp_path)]) == 0
    assert "Lift: too few failures to predict failure (7 successes, 1 failure;" in capsys.readouterr().out
    (row,) = list(csv.DictReader((tmp_path / "failures.csv").open()))
    quoted = (f"| {row['furthest_phase']} | {row['stall_step']} | {row['passed_median']} | {row['furthest']} |")
    guide = (repo / "docs/diagnose.md").read_text()
    assert quoted in guide and f"one failure (seed {row['seed']})" in guide, quoted


def test_the_package_functions_survive_importing_its_modules():
    """A submodule named like a package function replaces it once imported (`write` was both): the report's sections
    import the output module, and diagnose then failed with exit 5 in the same process."""
    import harness.analysis.diagnose as D
    import harness.analysis.diagnose.outputs  # noqa: F401
    from harness.report import early_warning  # noqa: F401

    assert callable(D.write) and callable(D.diagnose)


def test_diagnose_refuses_a_folder_that_is_no_run_in_one_line(tmp_path, capsys):
    from harness import cli

    assert cli.main(["diagnose", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not an octo-harness run folder" in err[0]
    assert cli.main(["diagnose", str(tmp_path), "--folds", "1"]) == 2
    assert "--folds must be at least 2" in capsys.readouterr().err

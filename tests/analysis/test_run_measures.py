"""Report analysis on inputs whose answers are known: bootstrap intervals, attention measures (shares, mask mass
and lift, entropy, per head), progress bins, aggregation by outcome, and the run-folder reader."""

import json

import numpy as np
import pytest

from harness.analysis import aggregate as agg
from harness.analysis.bootstrap import bootstrap_mean_ci
from harness.analysis.runs import NotARunError, load_run
from harness.measures.attention import mask_area_fraction, mask_fractions, step_metrics
from harness.measures.episode import episode_measures
from harness.octo.tokens import build_token_map
from harness.runfolder.schema import protocol_hash

# a small Octo-like layout: 3 language tokens, window 2 x (primary 4x4, wrist 2x2, 2 language, 1 readout)
TOKENS = build_token_map(
    [("task_language", 3)],
    [("obs_primary", 16), ("obs_wrist", 4), ("obs_task_language", 2), ("readout_action", 1)],
    window=2,
    image_groups=(("obs_primary", "image_primary", 4, 4), ("obs_wrist", "image_wrist", 2, 2)),
)
K = TOKENS.num_keys  # 3 + 2 * 23 = 49


def _current_primary() -> np.ndarray:
    return np.flatnonzero((TOKENS.group == "obs_primary") & (TOKENS.timestep == 1))


def _target_mask() -> np.ndarray:
    """32x32 pixel mask covering patches (1, 1) and (1, 2) of the 4x4 grid fully: area 2/16."""
    mask = np.zeros((32, 32), bool)
    mask[8:16, 8:24] = True
    return mask


def _measures(attn, masks=None):
    """attn (steps, layers, heads, readouts, keys); masks: the same {obs: {name: mask}} at every step."""
    steps = attn.shape[0]
    fr = [mask_fractions(TOKENS, masks) for _ in range(steps)]
    fractions = {k: np.stack([f[k] for f in fr]) for k in fr[0]} if masks else {}
    areas = {f"{o}/{n}": np.full(steps, mask_area_fraction(m)) for o, d in (masks or {}).items() for n, m in d.items()}
    return episode_measures(attn, TOKENS, fractions, areas)


# ---- bootstrap -------------------------------------------------------------------------------------------------


def test_bootstrap_of_constant_data_is_a_point():
    mean, low, high, n = bootstrap_mean_ci(np.full((7, 3), 0.25))
    np.testing.assert_array_equal(mean, 0.25)
    np.testing.assert_array_equal(low, 0.25)
    np.testing.assert_array_equal(high, 0.25)
    np.testing.assert_array_equal(n, 7)


def test_bootstrap_is_seeded_and_matches_the_normal_approximation_for_many_episodes():
    rng = np.random.default_rng(1)
    values = rng.normal(2.0, 1.0, size=(400, 1))
    a = bootstrap_mean_ci(values, seed=3)
    b = bootstrap_mean_ci(values, seed=3)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)  # deterministic
    mean, low, high, _ = a
    half = 1.96 * values.std(ddof=1) / np.sqrt(400)
    assert low[0] < mean[0] < high[0]
    np.testing.assert_allclose([mean[0] - low[0], high[0] - mean[0]], [half, half], rtol=0.15)


def test_bootstrap_leaves_nan_out_and_gives_no_interval_for_one_value():
    values = np.array([[1.0, np.nan], [3.0, np.nan], [np.nan, 5.0]])
    mean, low, high, n = bootstrap_mean_ci(values)
    np.testing.assert_array_equal(n, [2, 1])
    np.testing.assert_allclose(mean, [2.0, 5.0])
    assert 1.0 <= low[0] <= high[0] <= 3.0
    assert np.isnan(low[1]) and np.isnan(high[1])


# ---- episode measures --------------------------------------------------------------------------------------------


def test_all_attention_inside_the_target_gives_mass_one_and_lift_one_over_area():
    attn = np.zeros((2, 1, 2, 1, K), np.float32)
    inside = _current_primary()[[5, 6]]  # patches (1, 1) and (1, 2), row-major
    attn[..., inside] = 0.5
    m = _measures(attn, {"image_primary": {"target": _target_mask()}})
    area = 2 / 16
    np.testing.assert_allclose(m.layer["mask_mass/image_primary/target"], 1.0)
    np.testing.assert_allclose(m.layer["mask_lift/image_primary/target"], 1 / area)
    np.testing.assert_allclose(m.head["mask_lift/image_primary/target"], 1 / area)
    np.testing.assert_allclose(m.layer["share/primary"], 1.0)


def test_uniform_attention_gives_lift_one_and_entropy_log_keys():
    attn = np.full((3, 2, 2, 1, K), 1.0 / K, np.float16)
    m = _measures(attn, {"image_primary": {"target": _target_mask()}, "image_wrist": {"target": np.eye(16, dtype=bool)}})
    np.testing.assert_allclose(m.layer["mask_lift/image_primary/target"], 1.0, rtol=1e-3)
    np.testing.assert_allclose(m.head["mask_lift/image_primary/target"], 1.0, rtol=1e-3)
    np.testing.assert_allclose(m.layer["entropy"], np.log(K), rtol=1e-3)
    np.testing.assert_allclose(m.layer["share/primary"], 32 / K, rtol=1e-3)


def test_shares_sum_to_one_and_layer_level_matches_step_metrics():
    rng = np.random.default_rng(0)
    attn = rng.random((4, 3, 2, 2, K)).astype(np.float32)
    attn /= attn.sum(-1, keepdims=True)
    mask = _target_mask()
    m = _measures(attn, {"image_primary": {"target": mask, "robot": ~mask}})
    shares = sum(v for k, v in m.head.items() if k.startswith("share/"))
    np.testing.assert_allclose(shares, 1.0, atol=1e-6)
    parts = sum(v for k, v in m.layer.items() if k.startswith("timestep_share/"))
    np.testing.assert_allclose(parts, 1.0, atol=1e-6)
    for t in range(4):  # the numbers metrics.jsonl holds for that step
        ref = step_metrics(attn[t], TOKENS, {"image_primary": {"target": mask, "robot": ~mask}})
        for name in ("share/primary", "share/language", "timestep_share/earlier", "entropy",
                     "mask_mass/image_primary/target", "mask_mass/image_primary/robot"):
            np.testing.assert_allclose(m.layer[name][t], ref[name], rtol=1e-5, err_msg=name)


def test_per_head_mask_mass_separates_heads():
    attn = np.zeros((1, 1, 2, 1, K), np.float32)
    cam = _current_primary()
    attn[0, 0, 0, 0, cam[5]] = 1.0  # head 0: on the target
    attn[0, 0, 1, 0, cam[0]] = 1.0  # head 1: a corner patch, off the target
    m = _measures(attn, {"image_primary": {"target": _target_mask()}})
    np.testing.assert_allclose(m.head["mask_mass/image_primary/target"][0, 0], [1.0, 0.0])
    np.testing.assert_allclose(m.layer["mask_mass/image_primary/target"][0, 0], 0.5)  # head-mean map


def test_float16_entropy_table_matches_direct_entropy():
    rng = np.random.default_rng(2)
    attn = rng.dirichlet(np.full(K, 0.3), size=(2, 2, 3, 1)).astype(np.float16)
    a = episode_measures(attn, TOKENS)
    b = episode_measures(attn.astype(np.float64), TOKENS)
    np.testing.assert_allclose(a.head["entropy"], b.head["entropy"], atol=1e-6)


def test_step_without_a_mask_has_no_mass_and_runs_without_masks_have_no_mask_metrics():
    attn = np.full((2, 1, 1, 1, K), 1.0 / K, np.float32)
    frac = mask_fractions(TOKENS, {"image_primary": {"target": _target_mask()}})["image_primary/target"]
    fractions = {"image_primary/target": np.stack([frac, np.full_like(frac, np.nan)])}
    m = episode_measures(attn, TOKENS, fractions, {"image_primary/target": np.array([0.125, np.nan])})
    assert np.isfinite(m.layer["mask_mass/image_primary/target"][0]).all()
    assert np.isnan(m.layer["mask_mass/image_primary/target"][1]).all()
    assert not any(k.startswith("mask_") for k in episode_measures(attn, TOKENS).layer)


# ---- progress, summaries, aggregation ----------------------------------------------------------------------------


def test_progress_bins_and_binned_mean():
    np.testing.assert_array_equal(agg.progress_bins(10, 5), [0, 0, 1, 1, 2, 2, 3, 3, 4, 4])
    np.testing.assert_array_equal(agg.progress_bins(3, 6), [0, 2, 4])
    out = agg.binned_mean(np.arange(10.0)[:, None], 5)
    np.testing.assert_allclose(out[:, 0], [0.5, 2.5, 4.5, 6.5, 8.5])
    short = agg.binned_mean(np.array([1.0, 2.0, 3.0]), 6)
    np.testing.assert_array_equal(np.isnan(short), [False, True, False, True, False, True])


def _summary(value: float, lift: bool = True) -> agg.EpisodeSummary:
    layer = {"entropy": np.array([value, 2 * value])}
    if lift:
        layer["mask_lift/image_primary/target"] = np.array([value, value])
    return agg.EpisodeSummary(steps=4, layer=layer, head={"entropy": np.full((2, 3), value)},
                              progress={k: np.full((5, 2), value) for k in layer})


def test_aggregate_splits_by_outcome_and_skips_metrics_no_episode_has():
    summaries = [_summary(1.0), _summary(2.0), _summary(4.0, lift=False)]
    rows = agg.aggregate_task(summaries, [True, True, False], "r", "Lift")
    layer = {(r[8], r[4], r[2]): r for r in rows["layers"]}
    assert layer[("all", "entropy", 1)][5] == pytest.approx(2 * 7 / 3)
    assert layer[("success", "entropy", 0)][5] == pytest.approx(1.5)
    assert layer[("no_success", "entropy", 0)][5] == pytest.approx(4.0)
    assert layer[("all", "mask_lift/image_primary/target", 0)][9] == 2  # n: the episode without masks is left out
    assert ("no_success", "mask_lift/image_primary/target", 0) not in layer  # absent, not zero
    assert all(r[3] == agg.HEAD_MEAN for r in rows["layers"])
    assert {r[3] for r in rows["heads"]} == {0, 1, 2}
    assert len(rows["progress"]) == 3 * 5 * 2 * 2 - 5 * 2  # outcomes x bins x layers x metrics, minus the absent split
    assert rows["progress"][0][-3:] == (0, 0.0, 0.2)


def test_episodes_of_other_layer_counts_are_one_line_naming_a_fresh_restore_of_kept_runs():
    """A grid kept by scripts/keep_grid_runs.py (the last layer only) and finished after restoring holds both shapes in
    one run; the refusal names that case and its fix, not only "mixed models"."""
    cut = agg.EpisodeSummary(steps=4, layer={"entropy": np.array([1.0])}, head={}, progress={})
    fix = r"of shape \(1,\), others \(2,\).*keep_grid_runs.*restore the kept copy into an empty folder"
    with pytest.raises(ValueError, match=fix):
        agg.aggregate_task([cut, _summary(1.0)], [True, False], "r", "Lift")


def test_representative_is_closest_to_the_median():
    assert agg.representative_index(np.array([5.0, 1.0, 3.0, np.nan, 2.0])) == 2  # median 2.5: 3.0 and 2.0 tie -> first
    assert agg.representative_index(np.array([np.nan, np.nan])) == 0


# ---- run folders ----------------------------------------------------------------------------------------------------


def _store_run(path, rows, jobs, status="running", is_random=True):
    path.mkdir(parents=True)
    protocol = {"tasks": sorted({j[0] for j in jobs}), "episodes": 2, "seed": 0}
    manifest = {"format": "octo-harness-run/1", "run": path.name, "jobs": jobs, "protocol": protocol,
                "protocol_hash": protocol_hash(protocol),
                "model": {"source": "random:octo-small-1.5", "is_random": is_random, "text_tokenizer": "t5-base",
                          "dataset_key": None}, "versions": {"jax": "0.7.1"}}
    (path / "manifest.json").write_text(json.dumps(manifest))
    (path / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"task": "Li')  # a line being written
    (path / "results.json").write_text(json.dumps({"status": status}))


def test_store_run_reader_counts_missing_jobs_and_last_line_wins(tmp_path):
    jobs = [["Lift", 0, 0], ["Lift", 1, 1], ["Stack", 0, 0], ["Stack", 1, 1]]
    rows = [{"task": "Lift", "episode": 0, "seed": 0, "status": "failed", "success": False, "steps": 0,
             "directory": "Lift/episode_0", "error": "boom"},
            {"task": "Stack", "episode": 1, "seed": 1, "status": "ok", "success": True, "steps": 9,
             "directory": "Stack/episode_1"},
            {"task": "Lift", "episode": 0, "seed": 0, "status": "ok", "success": True, "steps": 5,
             "directory": "Lift/episode_0"}]
    _store_run(tmp_path / "r", rows, jobs)
    run = load_run(tmp_path / "r")
    assert run.status == "running" and run.model.is_random and run.model.text_tokenizer == "t5-base"
    assert [(e.task, e.episode, e.status) for e in run.episodes] == [("Lift", 0, "ok"), ("Stack", 1, "ok")]
    assert run.missing == 2 and run.missing_by_task() == {"Lift": 1, "Stack": 1}
    assert run.episodes[0].directory == (tmp_path / "r" / "Lift" / "episode_0").resolve()


def test_legacy_results_json_is_read(tmp_path):
    run_dir = tmp_path / "old"
    run_dir.mkdir()
    rows = [{"task": "Lift", "episode": 0, "seed": 3, "status": "ok", "success": False, "steps": 4,
             "directory": "/somewhere/else/Lift/episode_0"}]
    (run_dir / "results.json").write_text(json.dumps({"manifest": {"model": "random:octo-base-1.5", "model_is_random": True,
                                                                    "tasks": ["Lift"], "episodes": 2, "seed": 3},
                                                       "episodes": rows}))
    run = load_run(run_dir)
    assert run.format == "legacy" and run.status == "incomplete" and run.missing == 1
    assert run.model.source == "random:octo-base-1.5" and run.model.is_random
    assert run.jobs == (("Lift", 0, 3), ("Lift", 1, 4))


@pytest.mark.parametrize("case", ["missing", "file", "empty", "parent"])
def test_a_folder_that_is_not_a_run_is_one_line(tmp_path, case):
    target = tmp_path / "x"
    if case == "file":
        target.write_text("hi")
    elif case == "empty":
        target.mkdir()
    elif case == "parent":
        _store_run(target / "run_a", [], [["Lift", 0, 0]])
    with pytest.raises(NotARunError) as err:
        load_run(target)
    message = str(err.value)
    assert "\n" not in message and str(target) in message
    if case == "parent":
        assert "run_a" in message

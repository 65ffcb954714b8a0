"""The robustness measures on the content-only attention (issue 43 item 4), on hand-made maps with a known answer: a
map whose nuisance attention is all bound to position (it stays on the blank frame) shows it raw and not content-only;
the report says which map each figure uses."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from harness.analysis import robustness as R
from harness.analysis import robustness_measures as M
from harness.octo.tokens import TokenMap
from harness.report import robustness as report

ROWS = COLS = 4
LEFT = np.zeros((ROWS, COLS))
LEFT[:, 0] = 1.0  # the background: the left column
TARGET = np.zeros((ROWS, COLS))
TARGET[1, 2] = 1.0  # the target: one patch


def _map(left: float, target: float, rest: float = 0.0) -> np.ndarray:
    """A camera map: `left` spread over the left column, `target` on the target patch, `rest` over the other 11."""
    m = np.full((ROWS, COLS), rest / 11)
    m[:, 0] = left / 4
    m[1, 2] = target
    return m


def test_position_bound_nuisance_shows_raw_and_not_content_only():
    real = np.stack([_map(0.6, 0.4)] * 3)  # (steps, rows, cols)
    blank = np.stack([_map(0.6, 0.0, 0.4)] * 3)  # the left column's attention stays without content: position-bound
    fractions = {"background": np.stack([LEFT] * 3), "target": np.stack([TARGET] * 3)}
    raw_nuisance = (real * fractions["background"]).sum(axis=(1, 2)) / real.sum(axis=(1, 2))
    assert np.allclose(raw_nuisance, 0.6)
    out = M.content_means(real, blank, fractions, np.array([0, 5, 10]))
    assert out["nuisance_content"] == 0.0
    assert out["target_lift_content"] == pytest.approx(16.0)  # all content-bound attention on 1 of 16 patches
    assert out["nuisance_start_content"] == 0.0  # steps 0 and 5 (< START_STEPS)


def test_content_bound_nuisance_stays_content_only():
    real = np.stack([_map(0.6, 0.4)] * 2)
    blank = np.full((2, ROWS, COLS), 1 / 16)  # a blank frame spreads attention evenly: little is position-bound
    out = M.content_means(real, blank, {"background": np.stack([LEFT] * 2), "distractor_0": np.zeros((2, ROWS, COLS))},
                          np.array([20, 25]))
    # content: left column 4 x (0.15 - 1/16), target 0.4 - 1/16, the rest 0
    assert out["nuisance_content"] == pytest.approx(0.35 / (0.35 + 0.4 - 1 / 16))
    assert math.isnan(out["target_lift_content"]) and math.isnan(out["nuisance_start_content"])  # no target, no start


def _tokens() -> TokenMap:
    """language, a 4x4 primary camera and one readout, one timestep."""
    n = ROWS * COLS
    return TokenMap(group=np.array(["task_language"] + ["obs_primary"] * n + ["readout_action"]),
                    timestep=np.array([-1] + [0] * (n + 1), np.int32),
                    row=np.array([-1] + [i // COLS for i in range(n)] + [-1], np.int32),
                    col=np.array([-1] + [i % COLS for i in range(n)] + [-1], np.int32),
                    image_groups=(("obs_primary", "image_primary", ROWS, COLS),), readout_index=np.array([n + 1], np.int32))


def _rows(camera_map: np.ndarray, steps: int) -> np.ndarray:
    """(steps, layers 2, heads 2, readouts 1, keys): half the row on the camera (as `camera_map`), half elsewhere."""
    row = np.concatenate([[0.3], 0.5 * camera_map.ravel() / camera_map.sum(), [0.2]])
    return np.broadcast_to(row, (steps, 2, 2, 1, row.size)).astype(np.float16)


def _episode(directory, seed: int, success: bool, controls: bool, steps: int = 12):
    directory.mkdir(parents=True)
    real = _map(0.6, 0.4)
    masses = {"background": 0.6, "target": 0.4}
    arrays = {"step": np.arange(steps), **_tokens().to_arrays(), "readout_attention": _rows(real, steps),
              "mask_fraction/image_primary/background": np.broadcast_to(LEFT, (steps, ROWS, COLS)).astype(np.float32),
              "mask_fraction/image_primary/target": np.broadcast_to(TARGET, (steps, ROWS, COLS)).astype(np.float32),
              "measures/layer/mask_mass/image_primary/background": np.full((steps, 2), masses["background"], np.float32),
              "measures/layer/mask_lift/image_primary/target": np.full((steps, 2), 16 * masses["target"], np.float32)}
    np.savez(directory / "attention.npz", **arrays)
    if controls:
        control_steps = np.arange(0, steps, 5)
        np.savez(directory / "controls.npz", step=control_steps, blank=_rows(_map(0.6, 0.0, 0.4), len(control_steps)),
                 mirror=_rows(real[:, ::-1], len(control_steps)))
    return SimpleNamespace(ok=True, attention_path=directory / "attention.npz", directory=directory, task="Lift",
                           seed=seed, episode=seed, status="ok", success=success)


def _run(tmp_path, name: str, perturb, controls: str | None, outcomes):
    episodes = [_episode(tmp_path / name / f"ep{s}", s, ok, controls is not None and "blank" in controls)
                for s, ok in enumerate(outcomes)]
    policy = {"attention_controls": controls} if controls else {}
    return SimpleNamespace(name=name, manifest={"protocol": {"perturb": perturb, "policy": policy}}, episodes=episodes)


def test_a_grid_with_controls_reports_both_maps(tmp_path):
    outcomes = [True, False, True, True, False, True]
    records = [_run(tmp_path, "nominal", None, "blank,mirror", outcomes),
               _run(tmp_path, "lighting-1", "lighting:1", "blank,mirror", outcomes[::-1])]
    rows, _, notes = R.collect(records)
    assert not notes and len(rows) == 12
    assert all(r.nuisance_mass == pytest.approx(0.6, abs=1e-3) for r in rows)  # raw: the stored measure
    assert all(r.nuisance_content == 0.0 and r.nuisance_start_content == 0.0 for r in rows)  # content-only: none
    assert all(r.target_lift_content == pytest.approx(16.0, rel=1e-3) for r in rows)
    association = R.association_rows(rows)
    assert [a[16] for a in association] == ["raw", "content"]

    text = report.markdown(records)
    assert "Each figure names its map" in text and "may include position-bound attention" in text
    assert "| nuisance mass (raw) |" in text and "| nuisance mass (content only) |" in text
    lighting = next(line for line in text.splitlines() if line.startswith("| lighting | 1 |"))
    assert lighting.endswith("| 6.40 | 0.600 | 0.000 | 16.00 | 0.000 |")  # raw lift, nuisance, distractors; content
    tables = report.tables(records)
    assert "map" in tables["robustness_association.csv"][0]
    assert {a[16] for a in tables["robustness_association.csv"][1]} == {"raw", "content"}


def test_a_grid_without_controls_keeps_the_raw_note_and_table(tmp_path):
    outcomes = [True, False, True, True, False, True]
    records = [_run(tmp_path, "nominal", None, None, outcomes), _run(tmp_path, "lighting-1", "lighting:1", None, outcomes)]
    rows, _, _ = R.collect(records)
    assert all(math.isnan(r.nuisance_content) for r in rows)
    assert [a[16] for a in R.association_rows(rows)] == ["raw"]
    text = report.markdown(records)
    assert "these runs had no --attention-controls, so the figures may include position-bound attention" in text
    assert "content only" not in text and "| target lift | nuisance mass | distractor mass |" in text
    assert "on the raw maps" not in text and "on the content-only maps" not in text


def test_a_mirror_only_run_says_it_cannot_remove_position(tmp_path):
    note = report.map_note([_run(tmp_path, "nominal", None, "mirror", [True])])
    assert "only the mirror control" in note and "may include position-bound attention" in note


@pytest.mark.slow
def test_a_real_grid_with_controls_gets_content_only_figures(fixtures_dir, tmp_path):
    """The tiny fixture model, Lift, 2 steps, one episode per cell, controls at every step: every episode gets
    content-only figures, and with an empty blank map the content-only nuisance mass is the stored raw measure at
    the control steps (the maps, tokens and masks are read the way the writer measured them)."""
    from harness import cli
    from harness.analysis.runs import load_run

    (tmp_path / "p.toml").write_text('attention_controls = "blank,mirror"\ncontrols_every = 1\n')
    out = tmp_path / "grid"
    assert cli.main(["robustness", "--model", str(fixtures_dir / "tiny"), "--task", "Lift", "--perturb", "lighting",
                     "--levels", "0,1", "--episodes", "1", "--max-steps", "2", "--protocol", str(tmp_path / "p.toml"),
                     "--fast-render", "--no-video", "--out", str(out)]) == 0
    records = [load_run(out / "nominal"), load_run(out / "lighting-1")]
    rows, _, notes = R.collect(records)
    assert not notes and len(rows) == 2
    assert all(math.isfinite(r.nuisance_content) and math.isfinite(r.nuisance_mass) for r in rows)
    episode = records[0].episodes[0]
    with np.load(episode.attention_path) as z, np.load(episode.directory / "controls.npz") as c:
        arrays = {k: z[k] for k in z.files}
        steps = c["step"]
        no_blank = M.content_measures(arrays["readout_attention"], arrays, steps, np.zeros_like(c["blank"]))
    stored = arrays["measures/layer/mask_mass/image_primary/background"][steps, -1]
    assert no_blank["nuisance_content"] == pytest.approx(float(np.mean(stored)), abs=2e-3)
    text = report.markdown(records)
    assert "| nuisance mass (raw) |" in text and "| nuisance mass (content only) |" in text

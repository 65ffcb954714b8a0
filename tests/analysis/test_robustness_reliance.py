"""Nuisance reliance per episode beside the nuisance attention mass: hand-made episode folders whose reliance.jsonl
rows have known shares give known episode means in the robustness rows and in robustness_episodes.csv; an episode
without the file leaves the four fields empty, and a damaged file is a note, not a crash."""

from __future__ import annotations

import csv
import io
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from harness.probes.reliance import reader as reliance
from harness.analysis import robustness as R
from harness.report import robustness as report
from harness.report.rundata import csv_bytes

FIELDS = ("nuisance_reliance", "background_reliance", "distractor_reliance", "nuisance_reliance_start")


def _reliance_rows(step: int, shares: dict, camera: str = "image_primary") -> list[dict]:
    return [{"run": "r", "task": "Lift", "episode": 0, "seed": 0, "step": step, "camera": camera, "region": region,
             "fill": "impute", "change": share, "area_fraction": 0.25, "reliance_per_pixel": share * 4,
             "reliance_share": share, "camera_change": 1.0} for region, share in shares.items()]


def _episode(directory, seed: int, success: bool, reliance: list[dict] | None, text: str | None = None):
    directory.mkdir(parents=True)
    steps = 4
    np.savez(directory / "attention.npz",
             **{"measures/layer/mask_mass/image_primary/background": np.full((steps, 2), 0.5, np.float32),
                "measures/layer/mask_mass/image_primary/distractor_0": np.full((steps, 2), 0.1, np.float32)})
    if reliance is not None:
        (directory / "reliance.jsonl").write_text("".join(json.dumps(r) + "\n" for r in reliance))
    if text is not None:
        (directory / "reliance.jsonl").write_text(text)
    return SimpleNamespace(ok=True, attention_path=directory / "attention.npz", directory=directory, task="Lift",
                           seed=seed, episode=seed, status="ok", success=success)


def test_episode_rows_carry_nuisance_reliance_beside_nuisance_mass(tmp_path):
    # step 0: background 0.2 + distractors 0.3; step 40 (after START_STEPS): background 0.1, distractors 0.1;
    # the wrist camera's rows must not count (the measure is on the primary camera, as the attention's)
    rows = (_reliance_rows(0, {"target": 0.5, "background": 0.2, "distractors": 0.3})
            + _reliance_rows(0, {"gripper": 0.1, "background": 0.9}, camera="image_wrist")
            + _reliance_rows(40, {"target": 0.8, "background": 0.1, "distractors": 0.1}))
    assert 40 >= R.START_STEPS
    episodes = [_episode(tmp_path / "nominal" / "ep0", 0, True, rows),
                _episode(tmp_path / "nominal" / "ep1", 1, False, None),
                _episode(tmp_path / "nominal" / "ep2", 2, False, None, text='{"step": 0, "camera": \n')]
    record = SimpleNamespace(name="nominal", manifest={"protocol": {"perturb": "lighting:1", "policy": {}}},
                             episodes=episodes)
    out, _, notes, *_ = report.analyse([record])  # robustness.collect, then reliance.add_reliance
    measured, plain, damaged = out
    assert measured.nuisance_mass == pytest.approx(0.6, abs=1e-6)  # the attention's measure is unchanged
    assert measured.nuisance_reliance == pytest.approx(0.35)  # mean of 0.5 and 0.2
    assert measured.background_reliance == pytest.approx(0.15)
    assert measured.distractor_reliance == pytest.approx(0.2)
    assert measured.nuisance_reliance_start == pytest.approx(0.5)  # step 0 only
    assert all(math.isnan(getattr(plain, f)) and math.isnan(getattr(damaged, f)) for f in FIELDS)
    assert damaged.nuisance_mass == pytest.approx(0.6, abs=1e-6)  # a damaged reliance file costs only its fields
    assert len(notes) == 1 and notes[0].startswith("nominal/Lift/episode_2: unreadable reliance.jsonl")

    columns, table = report.tables([record])["robustness_episodes.csv"]
    assert columns[-4:] == FIELDS
    csv_rows = list(csv.DictReader(io.StringIO(csv_bytes(columns, table).decode())))
    assert [float(csv_rows[0][f]) for f in FIELDS] == pytest.approx([0.35, 0.15, 0.2, 0.5])
    assert all(csv_rows[i][f] == "" for i in (1, 2) for f in FIELDS)  # empty when not measured


def test_add_reliance_leaves_rows_without_a_file_as_they_are(tmp_path):
    episodes = [_episode(tmp_path / "n" / "ep0", 0, True, None)]
    record = SimpleNamespace(name="n", manifest={"protocol": {"perturb": None, "policy": {}}}, episodes=episodes)
    rows, _, _ = R.collect([record])
    assert reliance.add_reliance(rows, [record]) == (rows, [])


def test_attention_regions_follow_the_region_table():
    # robosuite: robot is not a region beside gripper and arm; distractor_<i> join; the rest is task_objects
    robosuite = {"target": 0.3, "gripper": 0.1, "arm": 0.1, "robot": 0.2, "distractor_0": 0.1, "distractor_1": 0.05,
                 "background": 0.25}
    shares = reliance.attention_regions(robosuite, ["target", "gripper", "arm", "distractors", "task_objects",
                                                    "background"])
    assert shares == pytest.approx({"target": 0.3, "gripper": 0.1, "arm": 0.1, "distractors": 0.15,
                                    "task_objects": 0.1, "background": 0.25})
    # LIBERO: no background mask, so the remainder is the background; object.<name> masks are no region;
    # normalised over the regions the reliance rows hold (goal absent from them here)
    libero = {"target": 0.2, "robot": 0.2, "goal": 0.1, "distractors": 0.1, "object.bowl_1": 0.2}
    shares = reliance.attention_regions(libero, ["target", "robot", "distractors", "background"])
    assert shares == pytest.approx({"target": 0.2 / 0.9, "robot": 0.2 / 0.9, "distractors": 0.1 / 0.9,
                                    "background": 0.4 / 0.9})
    assert reliance.attention_regions({"target": float("nan")}, ["target"]) == {}

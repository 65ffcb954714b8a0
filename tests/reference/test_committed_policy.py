"""The committed reference policy (models/octo-reference-robosuite): it loads as an Octo checkpoint whose
parameters fit its config, carries its own tokenizer, T5 config and evaluation conventions, and succeeds
in a real closed-loop Lift episode run by the harness (success counted by the run store)."""

import json
from pathlib import Path

import numpy as np
import pytest

from harness.conventions import CheckpointConventions
from harness.octo import load_pretrained
from harness.octo.checkpoint import check_param_tree, read_params, select_step
from harness.octo.config import OctoConfig

MODEL = Path(__file__).resolve().parents[2] / "models" / "octo-reference-robosuite"
LIFT_SEED = 1  # an evaluation seed (0..49) on which the committed model lifts the cube (27 steps in the evaluation run)


@pytest.fixture(scope="module")
def model():
    return load_pretrained(str(MODEL))


def test_checkpoint_has_octo_save_pretrained_layout_and_fits_the_size_budget():
    for name in ("config.json", "dataset_statistics.json", "example_batch.msgpack", "t5-tiny/config.json",
                 "tokenizer/tokenizer.json", "harness.toml", "training_curve.csv", "training_curve.png"):
        assert (MODEL / name).is_file(), name
    step = select_step(MODEL, None)
    assert (MODEL / str(step) / "default" / "checkpoint").is_file()
    total = sum(p.stat().st_size for p in MODEL.rglob("*") if p.is_file())
    assert total <= 25 * 2**20


def test_parameter_tree_matches_config(model):
    config = OctoConfig.from_json(MODEL / "config.json")
    assert config.transformer.num_layers == model.config.transformer.num_layers
    raw = read_params(MODEL, select_step(MODEL, None))
    check_param_tree(model.params, raw)  # raises on any missing, unexpected or mis-shaped path
    assert "task_tokenizers_language" in raw["octo_transformer"]  # the T5 weights live inside the checkpoint


def test_tokenizer_statistics_and_conventions_come_from_the_checkpoint(model):
    assert model.text_tokenizer.tokenizer is not None and not model.text_tokenizer.is_fallback
    ids = model.text_tokenizer.encode(["pick up the red cube"])["input_ids"][0]
    assert ids[5] == 1 and ids[6] == 0 and np.all(ids[:5] > 2)  # 5 known words, </s>, padding
    stats = json.loads((MODEL / "dataset_statistics.json").read_text())["robosuite_reference"]
    assert stats["action"]["mask"] == [True] * 6 + [False]
    assert len(stats["proprio"]["mean"]) == 8 and stats["num_trajectories"] > 0
    conventions = CheckpointConventions.read(MODEL)
    assert conventions.env_options().action_space == "robosuite"
    assert conventions.policy_config().dataset_key == "robosuite_reference"


@pytest.mark.slow
def test_reference_policy_lifts_the_cube_in_the_harness(tmp_path):
    from harness.cli import main

    code = main(["run", "--model", str(MODEL), "--task", "Lift", "--episodes", "1", "--seed", str(LIFT_SEED),
                 "--max-steps", "60", "--png-every", "0", "--no-video", "--fast-render", "--out", str(tmp_path),
                 "--run-name", "reference"])
    assert code == 0
    (row,) = [json.loads(line) for line in (tmp_path / "reference" / "results.jsonl").read_text().splitlines()]
    assert row["status"] == "ok" and row["seed"] == LIFT_SEED
    assert row["success"] is True and row["steps"] < 60

"""Replay: a model open loop on a run's recorded inputs (`octo-harness replay`), on any machine.

Known answers: the reference policy replayed on the committed baseline's inputs is EQUIVALENT here (under another
machine's numerics, XLA capped at SSE4.2, through `regress`: tests/gate/test_committed_baseline.py); on the platform that recorded a run it is exactly 0; a candidate with one
weight tensor perturbed (Gaussian, std 1e-3) is CHANGED from step 0; a run without recorded inputs is one line,
exit 2. The pure maths (normalised action change, float16 JS) on hand-made inputs.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from harness.analysis.equivalence import Tolerances, action_change, action_scale, attention_change, first_change
from harness.cli import main
from harness.files import json_safe
from harness.gate.results import ReplayResult
from harness.policy import input_digest
from tests.runfolder.edits import drop_output, make_legacy, rehash

REPO = Path(__file__).resolve().parents[2]
BASELINE = REPO / "results" / "baselines" / "reference-lift"
MODEL = REPO / "models" / "octo-reference-robosuite"


def perturbed_model(dest: Path, std: float = 1e-3) -> Path:
    """A copy of the reference policy with Gaussian noise (std) added to one MLP kernel (a seeded draw)."""
    from flax import serialization

    shutil.copytree(MODEL, dest)
    (path,) = dest.glob("*/default/checkpoint")
    tree = serialization.msgpack_restore(path.read_bytes())
    node = tree["octo_transformer"]["BlockTransformer_0"]["Transformer_0"]["encoderblock_1"]["MlpBlock_0"]["Dense_1"]
    kernel = np.asarray(node["kernel"])
    node["kernel"] = (kernel + std * np.random.default_rng(0).standard_normal(kernel.shape)).astype(kernel.dtype)
    path.write_bytes(serialization.msgpack_serialize(tree))
    return dest


def _replay(argv, capsys) -> tuple[int, ReplayResult, str]:
    """The command's exit code, its replay.json read back as a ReplayResult (which writes the file's JSON again, key
    for key), and its output."""
    code = main(["replay", *argv])
    out = capsys.readouterr().out
    path = Path(out.strip().splitlines()[-1].split("replay: ", 1)[1])
    data = json.loads(path.read_text())
    result = ReplayResult.from_json(data)
    assert json_safe(result.to_json()) == data
    return code, result, out


# ------------------------------------------------------------------------------------------- pure maths

def test_action_change_is_in_normalised_units_and_masked_dims_stay_raw():
    stats = {"mean": np.zeros(3), "std": np.array([0.5, 2.0, 1.0]), "mask": np.array([True, True, False])}
    scale = action_scale(stats, "normal", 3)
    recorded = np.zeros((2, 4, 3))
    replayed = recorded.copy()
    replayed[0, 1] = [0.1, 0.0, 0.0]  # 0.1 / std 0.5 = 0.2 normalised
    replayed[1, 3] = [0.0, 0.2, 0.3]  # 0.2 / 2 = 0.1; the masked gripper dim raw: 0.3
    np.testing.assert_allclose(action_change(recorded, replayed, scale), [0.2, 0.3], rtol=1e-6)
    bounds = action_scale({"p01": np.array([-1.0, 0, 0]), "p99": np.array([1.0, 4, 2])}, "bounds", 3)
    np.testing.assert_allclose(bounds, [1.0, 2.0, 1.0], rtol=1e-6)  # half the p01..p99 range
    np.testing.assert_array_equal(action_scale(None, "normal", 3), np.ones(3))


def test_attention_change_is_float16_js_and_the_first_change_is_found():
    rng = np.random.default_rng(0)
    a = rng.dirichlet(np.ones(16), size=(3, 2, 2, 1))  # (steps, layers, heads, readouts, keys)
    stored = a.astype(np.float16)  # what attention.npz holds
    assert attention_change(stored, a).max() == 0.0  # a float32 row and its float16 copy compare equal
    b = a.copy()
    b[2, 1, 0, 0] = np.roll(b[2, 1, 0, 0], 1)
    js = attention_change(a, b)  # (steps, layers, heads)
    assert js.shape == (3, 2, 2) and js[2, 1, 0] > 1e-3 and js[:2].max() == 0.0
    tol = Tolerances(action=1e-4, attention_js=1e-6)
    assert first_change(np.zeros(3), js, tol) == 2
    assert first_change(np.array([0.0, 5e-4, 0.0]), np.zeros((3, 2, 2)), tol) == 1
    assert first_change(np.zeros(3), np.zeros((3, 2, 2)), tol) is None
    assert first_change(np.array([0.0, np.nan, 0.0]), np.zeros((3, 2, 2)), tol) == 1  # NaN actions: changed
    nan_js = np.zeros((3, 2, 2))
    nan_js[2, 0, 1] = np.nan
    assert first_change(np.zeros(3), nan_js, tol) == 2
    with pytest.raises(ValueError, match="tolerances must be >= 0"):
        Tolerances(action=-1.0)


def test_the_baseline_records_what_the_policy_saw_and_its_digest():
    with np.load(BASELINE / "Lift" / "episode_1" / "inputs.npz") as inputs, \
            np.load(BASELINE / "Lift" / "episode_1" / "actions.npz") as actions:
        assert int(inputs["seed"]) == 1 and str(inputs["instruction"])
        frames = inputs["input/image_primary"]  # (steps, H, W, 3) uint8 at the model's size
        assert frames.dtype == np.uint8 and frames.shape[1:] == (128, 128, 3) and frames.shape[0] == 20  # primary
        hashes = actions["input_hash/image_primary"]
        assert [input_digest(f) for f in frames] == [int(h) for h in hashes[:20]]
        assert len(set(int(h) for h in hashes[:20])) == 20  # a new frame every step


# ------------------------------------------------------------------------------------------- the command

def test_replaying_the_baseline_with_its_own_model_is_equivalent(capsys, tmp_path):
    code, result, out = _replay([str(BASELINE), "--model", str(MODEL), "--out", str(tmp_path)], capsys)
    assert code == 0 and result.verdict == "EQUIVALENT", out
    assert result.episodes == 8 and result.steps_compared >= 8 * 19
    tol = result.tolerances
    assert result.action_change_max <= tol.action and result.attention_js_max <= tol.attention_js
    from harness.runfolder.platform import platform_fingerprint, platform_info

    if platform_fingerprint(platform_info()) == result.platform_recorded:
        assert result.action_change_max == 0.0 and result.attention_js_max == 0.0  # the recording platform: bits


@pytest.mark.slow
def test_a_candidate_with_one_weight_tensor_perturbed_is_changed_from_step_0(capsys, tmp_path):
    candidate = perturbed_model(tmp_path / "perturbed")
    code, result, out = _replay([str(BASELINE), "--model", str(candidate), "--out", str(tmp_path / "r")], capsys)
    assert code == 1 and result.verdict == "CHANGED"
    first = result.first_change
    assert first.first_changed_step == 0 and first.change_at_first.action > result.tolerances.action
    assert "first change: Lift episode" in out and "step 0" in out
    assert result.episodes_changed == result.episodes == 8


def test_a_run_without_recorded_inputs_is_one_line_and_exit_2(tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(BASELINE, run)
    drop_output(run, "inputs.npz")  # a run made without --record-inputs
    assert main(["replay", str(run), "--model", str(MODEL)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no inputs.npz; replay needs a run made with --record-inputs" in err[0]


def test_a_run_whose_model_is_not_here_names_the_fix(tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(BASELINE, run)
    manifest = json.loads((run / "manifest.json").read_text())
    manifest["protocol"]["model"] = str(tmp_path / "gone")
    (run / "manifest.json").write_text(json.dumps(manifest))
    rehash(run)  # a run made where the model was, not a hand-edited manifest
    assert main(["replay", str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not on this machine" in err[0] and "pass the model to replay with --model" in err[0]


@pytest.mark.slow
@pytest.mark.parametrize("intervention", ["mask-top:4:attention:2", "ablate-heads:1:0"])
def test_intervention_runs_replay_exactly_on_the_inputs_the_policy_saw(intervention, tmp_path, capsys):
    """A masking intervention records the masked frames (what the policy saw), so replay does not mask again; a head
    ablation is part of the model the replay runs."""
    common = ["run", "--model", str(MODEL), "--task", "Lift", "--episodes", "1", "--max-steps", "5", "--fast-render",
              "--png-every", "0", "--no-video", "--record-inputs", "--out", str(tmp_path), "--run-name", "iv",
              "--intervene", intervention]
    assert main(common) == 0
    capsys.readouterr()
    code, result, out = _replay([str(tmp_path / "iv"), "--out", str(tmp_path / "r")], capsys)
    assert code == 0 and result.verdict == "EQUIVALENT" and result.steps_compared == 5, out
    assert result.action_change_max == 0.0 and result.attention_js_max == 0.0


@pytest.mark.slow
def test_replay_tokenizes_the_instruction_as_the_run_did(tmp_path, capsys):
    """A run made with --text-tokenizer fallback replays with that tokenizer (else the comparison measures the
    tokenizer, not the model)."""
    assert main(["run", "--model", str(MODEL), "--task", "Lift", "--episodes", "1", "--max-steps", "3", "--fast-render",
                 "--png-every", "0", "--no-video", "--record-inputs", "--out", str(tmp_path), "--run-name", "fb",
                 "--text-tokenizer", "fallback"]) == 0
    capsys.readouterr()
    code, result, out = _replay([str(tmp_path / "fb"), "--out", str(tmp_path / "r")], capsys)
    assert code == 0 and result.action_change_max == 0.0, out


@pytest.mark.slow
def test_a_candidate_that_outputs_nan_is_changed_not_equivalent(capsys, tmp_path):
    """NaN compares false with any tolerance; replay must count it as a change."""
    candidate = perturbed_model(tmp_path / "nan", std=float("nan"))
    code, result, out = _replay([str(BASELINE), "--model", str(candidate), "--out", str(tmp_path / "r")], capsys)
    assert code == 1 and result.verdict == "CHANGED" and result.first_change.first_changed_step == 0, out


@pytest.mark.parametrize("legacy, found", [(False, "is damaged (200 bytes, its row records"),
                                           (True, "is damaged or incomplete")])
@pytest.mark.parametrize("name", ["inputs.npz", "attention.npz"])
def test_a_damaged_recorded_file_is_one_line_and_exit_2(name, legacy, found, tmp_path, capsys):
    """Found by its recorded size and digest, or, in rows made before those were recorded, by its reader."""
    run = tmp_path / "run"
    shutil.copytree(BASELINE, run)
    if legacy:
        make_legacy(run)
    path = run / "Lift" / "episode_3" / name
    path.write_bytes(path.read_bytes()[:200])  # cut short, as a full disk leaves it
    assert main(["replay", str(run), "--model", str(MODEL)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"episode_3/{name} {found}" in err[0]

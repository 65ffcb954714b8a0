"""The per-step signals of issue 74 as probes: readout features (--readout-features-every) and action consistency
(--action-consistency, --action-samples). The measure on hand-made chunks with known numbers; the sinks and readers on
hand-made records; the options and the refusal of sampling again from a deterministic head, before any episode; and
two real runs of the tiny fixture sharing one loaded model, without and with both probes, whose executed actions are
bit-identical and whose probe files hold what the readers give back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from harness import probes
from harness.policy import PolicyConfig
from harness.probes.action_consistency import measure
from tests.outputs.test_sinks import STEPS, drive, files_in, with_extras
from tests.outputs.test_writers import records

# ------------------------------------------------------------------------------------------- the measure


def test_disagreement_on_hand_made_chunks_gives_the_known_numbers():
    """Horizon 4, 2 dims, the new chunk all zeros: the chunk of age 1 planned |1 2|3 4|5 6| for its steps 1..3
    (mean 3.5), the chunk of age 2 |1 1|1 1| for steps 2..3 (mean 1); age 4 overlaps nothing. Over every overlapping
    pair: (21 + 4) / 10 = 2.5, per dim (9 + 2) / 5 = 2.2 and (12 + 2) / 5 = 2.8."""
    now = np.zeros((4, 2))
    age1 = np.array([[9, 9], [1, 2], [3, 4], [5, 6]], float)
    age2 = np.array([[9, 9], [9, 9], [1, 1], [1, 1]], float)
    found = measure.disagreement(now, [(1, age1), (2, age2), (4, np.full((4, 2), 100.0))])
    assert found["disagreement"] == pytest.approx(2.5)
    np.testing.assert_allclose(found["dims"], [2.2, 2.8])
    np.testing.assert_allclose(found["by_age"], [3.5, 1.0, np.nan])
    alone = measure.disagreement(now, [])
    assert np.isnan(alone["disagreement"]) and np.isnan(alone["dims"]).all() and np.isnan(alone["by_age"]).all()
    # 7-D actions: translation, rotation, gripper apart; other dims: none
    assert measure.parts(np.array([1, 2, 3, 4, 5, 6, 7.0])) == {"translation": 2.0, "rotation": 5.0, "gripper": 7.0}
    assert measure.parts(np.ones(2)) == {}
    # spread: the executed chunk and one drawn again, 0 and 2 everywhere: a standard deviation of 1
    assert measure.spread(np.stack([np.zeros((4, 7)), np.full((4, 7), 2.0)]))["spread"] == pytest.approx(1.0)


def test_an_episode_of_recorded_chunks_compares_only_inferred_chunks_within_the_horizon():
    """A receding horizon of 2 over horizon 4: chunks inferred at steps 0, 2, 4 (steps 1, 3 reuse them); step 2's
    chunk meets step 0's at age 2, step 4's meets step 2's (step 0's is 4 steps old: outside the horizon)."""
    chunks = np.arange(5 * 4 * 1, dtype=np.float32).reshape(5, 4, 1)  # chunk s predicts s*4 + i for i = 0..3
    found = measure.episode([0, 1, 2, 3, 4], chunks, [True, False, True, False, True])
    assert found["step"].tolist() == [0, 2, 4] and np.isnan(found["disagreement"][0])
    # step 2: its chunk [8 9 10 11][:2] against step 0's [0 1 2 3][2:] -> |8-2|, |9-3| = 6
    np.testing.assert_allclose(found["disagreement"][1:], [6.0, 6.0])
    np.testing.assert_allclose(found["by_age"][1], [np.nan, 6.0, np.nan])
    assert found["dims"].shape == (3, 1) and found["by_age"].shape == (3, 3)


# ------------------------------------------------------------------------------------------- sinks and readers


def test_the_sinks_write_compact_files_that_the_readers_give_back(tmp_path):
    """readout_features.npz: float16 features at the probed steps; action_consistency.npz: the disagreement of each
    probed step's chunk with the records' earlier chunks, 7-D parts, and the spread where sampled; the same numbers
    from actions.npz (`from_actions`). No payload: no file."""
    from harness.outputs.data_files import ActionArrays

    rng = np.random.default_rng(1)
    features = {0: {"features": rng.normal(size=16).astype(np.float32)},
                2: {"features": rng.normal(size=16).astype(np.float32)}}
    spread_dims = np.linspace(0.1, 0.7, 7).astype(np.float32)
    consistency = {0: {}, 1: {}, 2: {"samples": 3, "spread": 0.4, "spread_dims": spread_dims}}
    recs = with_extras(records(STEPS), readout_features=features, action_consistency=consistency)

    _, files = drive(probes.part("readout_features", "sink"), tmp_path / "features", recs)
    assert files == {"readout_features": "readout_features.npz"}
    stored = np.load(tmp_path / "features" / "readout_features.npz")
    assert stored["features"].dtype == np.float16 and stored["features"].shape == (2, 16)
    assert stored["step"].tolist() == [0, 2] and stored["step"].dtype == np.int32
    read = probes.part("readout_features", "reader").by_step(tmp_path / "features")
    np.testing.assert_array_equal(read[2]["features"], features[2]["features"].astype(np.float16).astype(np.float32))

    _, files = drive(probes.part("action_consistency", "sink"), tmp_path / "c", recs)
    drive(ActionArrays, tmp_path / "c", recs)
    assert files == {"action_consistency": "action_consistency.npz"}
    stored = np.load(tmp_path / "c" / "action_consistency.npz")
    assert stored["by_age"].shape == (3, 3) and stored["dims"].shape == (3, 7)
    assert all(stored[k].dtype == np.float32 for k in ("disagreement", "translation", "rotation", "gripper", "spread"))
    reader = probes.part("action_consistency", "reader")
    read = reader.by_step(tmp_path / "c")
    chunks = [r.actions_predicted.astype(np.float64) for r in recs]
    want = measure.disagreement(chunks[2], [(1, chunks[1]), (2, chunks[0])])
    assert read[2]["disagreement"] == pytest.approx(want["disagreement"], rel=1e-6)
    assert read[2]["gripper"] == pytest.approx(want["dims"][6], rel=1e-6)
    assert np.isnan(read[0]["disagreement"]) and np.isnan(read[1]["spread"]) and read[2]["samples"] == 3
    np.testing.assert_array_equal(read[2]["spread_dims"], spread_dims)
    offline = reader.from_actions(tmp_path / "c")
    np.testing.assert_allclose(offline["disagreement"], stored["disagreement"], rtol=1e-6)

    (tmp_path / "none").mkdir()
    _, files = drive(probes.part("action_consistency", "sink"), tmp_path / "none", records(STEPS))
    assert files == {} and files_in(tmp_path / "none") == []
    assert reader.by_step(tmp_path / "none") == {} and probes.part("readout_features", "reader").by_step(tmp_path) == {}


def test_the_options_are_checked_and_left_out_of_the_protocol_when_off():
    assert probes.active(PolicyConfig()) == ()
    assert not {"readout_features_every", "action_consistency", "action_samples"} & set(PolicyConfig().to_dict())
    on = PolicyConfig(readout_features_every=3, action_consistency=True, action_samples=2)
    assert [(cls.name, cls.every(on)) for cls in probes.active(on)] == [("readout_features", 3), ("action_consistency", 1)]
    assert on.to_dict()["action_samples"] == 2 and on.to_dict()["readout_features_every"] == 3
    with pytest.raises(ValueError, match="--readout-features-every must be an integer >= 0"):
        PolicyConfig(readout_features_every=-1)
    with pytest.raises(ValueError, match="--action-samples needs --action-consistency"):
        PolicyConfig(action_samples=2)


def test_sampling_again_from_a_deterministic_head_is_one_line_before_any_episode(tmp_path, capsys):
    """The robosuite reference's L1 head gives the same chunk for every key: --action-samples is refused in one
    line naming the fix, and no run folder is made."""
    from harness import cli
    from harness.probes.action_consistency import samples_error
    from tests.conftest import REPO

    model = REPO / "models" / "octo-reference-robosuite"
    code = cli.main(["run", "--task", "Lift", "--model", str(model), "--out", str(tmp_path), "--max-steps", "2",
                     "--action-consistency", "--action-samples", "2", "--png-every", "0", "--no-video"])
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "--action-samples" in line]
    assert code == 2 and len(err) == 1 and "deterministic" in err[0] and "drop --action-samples" in err[0]
    assert not [p for p in tmp_path.rglob("episode.json")]
    assert samples_error(object(), 0) is None


# ------------------------------------------------------------------------------------------- real runs


@pytest.fixture(scope="module")
def runs(fixtures_dir, tmp_path_factory):
    """The tiny fixture (a diffusion head) on Lift, 5 steps, seed 3, once plain and once with both probes (features
    every 2nd step, consistency with 2 more draws), one loaded model (one compilation of the sampler)."""
    from harness.octo import load_pretrained
    from harness.outputs.writers import OutputOptions
    from harness.run import Protocol, execute

    model = load_pretrained(str(fixtures_dir / "tiny"))
    out = tmp_path_factory.mktemp("failure_probes")
    outputs = OutputOptions(png_every=0, video=False)
    on = PolicyConfig(readout_features_every=2, action_consistency=True, action_samples=2)
    for name, policy in (("plain", PolicyConfig()), ("probed", on)):
        protocol = Protocol(model=model.source, tasks=("Lift",), max_steps=5, seed=3, policy=policy, outputs=outputs)
        execute(protocol, out, name, model=model, progress=False, preflight="off")
    return out, model


@pytest.mark.slow
def test_the_probes_leave_the_executed_actions_bit_identical(runs):
    out, _ = runs
    plain, probed = (np.load(out / name / "Lift" / "episode_0" / "actions.npz") for name in ("plain", "probed"))
    assert plain["executed"].shape == (5, 7)
    for key in ("executed", "predicted", "inferred"):
        assert np.array_equal(plain[key], probed[key]), key
    assert files_in(out / "plain" / "Lift" / "episode_0") == ["actions.npz", "attention.npz", "episode.json",
                                                              "metrics.jsonl"]
    manifest = json.loads((out / "plain" / "manifest.json").read_text())["protocol"]["policy"]
    assert not {"readout_features_every", "action_consistency", "action_samples"} & set(manifest)


@pytest.mark.slow
def test_a_probed_run_writes_both_files_and_the_readers_give_them_back(runs):
    out, model = runs
    episode = out / "probed" / "Lift" / "episode_0"
    width = int(model.config.token_embedding_size)  # 64: what the head reads
    features = probes.part("readout_features", "reader").by_step(episode)
    assert sorted(features) == [0, 2, 4]
    assert {v["features"].shape for v in features.values()} == {(width,)}
    assert all(np.isfinite(v["features"]).all() and v["features"].any() for v in features.values())
    consistency = probes.part("action_consistency", "reader").by_step(episode)
    assert sorted(consistency) == [0, 1, 2, 3, 4] and np.isnan(consistency[0]["disagreement"])
    assert all(consistency[s]["disagreement"] > 0 and consistency[s]["spread"] > 0 for s in (1, 2, 3, 4))
    assert {c["samples"] for c in consistency.values()} == {2} and consistency[4]["by_age"].shape == (3,)
    offline = probes.part("action_consistency", "reader").from_actions(episode)
    np.testing.assert_allclose(offline["disagreement"][1:], [consistency[s]["disagreement"] for s in (1, 2, 3, 4)],
                               rtol=1e-6)
    files = json.loads((episode / "episode.json").read_text())["files"]
    assert files["readout_features"] == "readout_features.npz" and files["action_consistency"] == "action_consistency.npz"
    (row,) = [json.loads(line) for line in (out / "probed" / "results.jsonl").read_text().splitlines()]
    assert {"readout_features.npz", "action_consistency.npz"} <= set(row["files"])
    policy = json.loads((out / "probed" / "manifest.json").read_text())["protocol"]["policy"]
    assert (policy["readout_features_every"], policy["action_consistency"], policy["action_samples"]) == (2, True, 2)

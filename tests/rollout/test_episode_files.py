"""End to end with the real simulator and the real JAX model (the reference fixture checkpoint, 64/32 px inputs):
closed-loop episodes write overlays, MP4, arrays and results; same seed -> same actions, attention and images."""

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

import envs
from harness.policies import as_policy
from harness import cli
from harness.octo import load_pretrained
from harness.policy import PolicyConfig
from harness.run import Protocol, execute
from harness.outputs.writers import OutputOptions

STEPS = 3


@pytest.fixture(scope="module")
def tiny(fixtures_dir):
    return load_pretrained(str(fixtures_dir / "tiny"))


def _run(model, out: Path, name: str, **kw):
    protocol = Protocol(model=model.source, tasks=("Lift",), max_steps=STEPS, **kw)
    return execute(protocol, out, name, model=model, progress=False)


@pytest.fixture(scope="module")
def two_runs(tiny, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs")
    return _run(tiny, out, "a", seed=7), _run(tiny, out, "b", seed=7)


@pytest.mark.slow
def test_episode_writes_png_per_step_and_layer_and_mp4_with_one_frame_per_step(two_runs, tiny):
    summary = two_runs[0]
    (row,) = summary.rows
    assert row.status == "ok" and row.steps == STEPS
    episode = summary.episode_dir(row)
    layers = tiny.config.transformer.num_layers if hasattr(tiny.config, "transformer") else 2
    pngs = sorted(p.name for p in episode.glob("step_*_layer_*.png"))
    assert pngs == [f"step_{t:04d}_layer_{l:02d}.png" for t in range(STEPS) for l in range(layers)]
    frames = iio.imread(episode / "rollout.mp4", index=None)
    assert frames.shape[0] == STEPS
    meta = json.loads((episode / "episode.json").read_text())
    assert meta["steps"] == STEPS and meta["seed"] == 7 and meta["task"] == "Lift"
    assert meta["instruction"] == envs.get_task("Lift").instruction
    results = json.loads((summary.run_dir / "results.json").read_text())
    assert results["manifest"]["model"]["is_random"] is False
    assert [e["status"] for e in results["episodes"]] == ["ok"]
    assert not list(episode.glob("*.tmp*"))


@pytest.mark.slow
def test_saved_attention_has_every_step_layer_and_head(two_runs, tiny):
    episode = two_runs[0].episode_dir(two_runs[0].rows[0])
    with np.load(episode / "attention.npz") as z:
        readout = z["readout_attention"]  # (steps, layers, heads, readouts, keys)
        keys = z["tokens/group"].shape[0]
    assert readout.dtype == np.float16
    assert readout.shape[0] == STEPS and readout.shape[1:3] == (2, 4) and readout.shape[-1] == keys == 90
    np.testing.assert_allclose(readout.astype(np.float32).sum(-1), 1.0, atol=5e-3)


@pytest.mark.slow
def test_same_seed_gives_identical_actions_attention_and_images(two_runs):
    a, b = (s.episode_dir(s.rows[0]) for s in two_runs)
    for name in ("actions.npz", "attention.npz"):
        with np.load(a / name) as za, np.load(b / name) as zb:
            assert za.files == zb.files
            for key in za.files:
                np.testing.assert_array_equal(za[key], zb[key], err_msg=f"{name}:{key}")
    for png in sorted(a.glob("step_*.png")):
        assert png.read_bytes() == (b / png.name).read_bytes(), png.name


@pytest.mark.slow
def test_different_seed_gives_a_different_episode(tiny, two_runs, tmp_path):
    other = _run(tiny, tmp_path, "c", seed=8, outputs=OutputOptions(png_every=0, video=False))
    with np.load(two_runs[0].episode_dir(two_runs[0].rows[0]) / "actions.npz") as za, \
            np.load(other.episode_dir(other.rows[0]) / "actions.npz") as zc:
        assert not np.array_equal(za["predicted"], zc["predicted"])


def test_readout_rows_sum_to_one_over_unmasked_keys_and_skip_padded_timestep(tiny):
    env = envs.make("Lift")
    try:
        obs, info = env.reset(seed=0)
        policy = as_policy(tiny).closed_loop(PolicyConfig())
        policy.reset(info["instruction"], seed=0)
        step0 = policy.step(obs)  # window [obs0 (padded), obs0]
        obs, *_ = env.step(step0.action)
        step1 = policy.step(obs)  # window [obs0, obs1], nothing padded
    finally:
        env.close()
    tokens = tiny.token_map()
    padded = np.isin(tokens.group, ["obs_primary", "obs_wrist"]) & (tokens.timestep == 0)
    for step in (step0, step1):
        assert step.readout_attention.shape == (2, 4, 1, 90)
        np.testing.assert_allclose(step.readout_attention.sum(-1), 1.0, atol=1e-5)
    assert step0.readout_attention[..., padded].max() < 1e-6  # padded timestep's image keys are masked
    assert step1.readout_attention[..., padded].sum(-1).min() > 1e-4  # ... and attended once real
    assert step0.chunk.shape == (4, 7) and np.isfinite(step0.chunk).all()


@pytest.mark.slow
def test_failing_episode_is_recorded_and_the_run_goes_on(tiny, tmp_path, monkeypatch):
    """Episode 0 cannot create its output folder (an OSError, as a full or read-only disk gives): it is recorded as
    failed and episode 1 runs. (A plain file in an episode's place no longer fails it: the run store replaces it.)"""
    import harness.run.executor as executor

    class Blocked(executor.EpisodeWriter):
        def __init__(self, episode_dir, *args, **kwargs):
            if Path(episode_dir).name == "episode_0":
                raise OSError(f"[Errno 30] Read-only file system: '{episode_dir}'")
            super().__init__(episode_dir, *args, **kwargs)

    monkeypatch.setattr(executor, "EpisodeWriter", Blocked)
    summary = _run(tiny, tmp_path, "r", episodes=2, outputs=OutputOptions(png_every=0, video=False))
    assert [r.status for r in summary.rows] == ["failed", "ok"]
    assert "Read-only file system" in summary.rows[0].error and summary.rows[1].steps == STEPS
    results = json.loads((tmp_path / "r" / "results.json").read_text())
    assert [e["status"] for e in results["episodes"]] == ["failed", "ok"]


@pytest.mark.slow
def test_cli_runs_an_episode_and_rejects_an_unknown_task(fixtures_dir, tmp_path, capsys):
    code = cli.main(["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--max-steps", "2",
                     "--out", str(tmp_path), "--run-name", "cli", "--png-every", "2", "--layers", "1", "--fast-render"])
    out = capsys.readouterr().out
    assert code == 0 and "Lift" in out and "results:" in out
    assert sorted(p.name for p in (tmp_path / "cli" / "Lift" / "episode_0").glob("*.png")) == ["step_0000_layer_01.png"]
    code = cli.main(["run", "--task", "Lfit", "--model", str(fixtures_dir / "tiny"), "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "Lift" in err[0]  # names the closest task


def test_cli_lists_every_registered_task(capsys):
    assert cli.main(["tasks"]) == 0
    out = capsys.readouterr().out
    for spec in envs.list_tasks():
        assert spec.name in out and spec.instruction in out


@pytest.mark.slow
def test_goal_conditioned_model_needs_goal_images_and_runs_with_them(fixtures_dir, tmp_path, capsys):
    model = str(fixtures_dir / "tiny_goal")
    code = cli.main(["run", "--task", "Lift", "--model", model, "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--goal-images" in err[0] and "image_primary.png" in err[0]
    goals = tmp_path / "goals"
    goals.mkdir()
    rng = np.random.default_rng(0)
    iio.imwrite(goals / "image_primary.png", rng.integers(0, 256, (256, 256, 3), dtype=np.uint8))
    iio.imwrite(goals / "image_wrist.png", rng.integers(0, 256, (128, 128, 3), dtype=np.uint8))
    code = cli.main(["run", "--task", "Lift", "--model", model, "--goal-images", str(goals), "--max-steps", "2",
                     "--out", str(tmp_path), "--run-name", "goal", "--png-every", "0", "--no-video"])
    assert code == 0
    with np.load(tmp_path / "goal" / "Lift" / "episode_0" / "attention.npz") as z:
        groups = set(z["tokens/group"].tolist())
        assert z["readout_attention"].shape[0] == 2
    assert "task_language" not in groups and "obs_primary" in groups


@pytest.mark.slow
def test_receding_horizon_executes_k_actions_per_inference(tiny):
    env = envs.make("Lift", cameras={"image_primary": ("agentview", 64), "image_wrist": ("robot0_eye_in_hand", 32)})
    try:
        obs, info = env.reset(seed=3)
        policy = as_policy(tiny).closed_loop(PolicyConfig(execution="receding_horizon", receding_steps=2))
        policy.reset(info["instruction"], seed=3)
        steps = []
        for _ in range(4):
            steps.append(policy.step(obs))
            obs, *_ = env.step(steps[-1].action)
    finally:
        env.close()
    assert [s.inferred for s in steps] == [True, False, True, False]
    np.testing.assert_array_equal(steps[0].action, steps[0].chunk[0])
    np.testing.assert_array_equal(steps[1].action, steps[0].chunk[1])  # second action of the same chunk
    assert steps[1].readout_attention is steps[0].readout_attention  # attention of the chunk being executed
    assert not np.array_equal(steps[2].chunk, steps[0].chunk)

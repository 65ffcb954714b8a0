"""Finetuned checkpoints in the closed loop (real robosuite + real JAX model).

The checkpoint is built here in the shape of Octo's finetuning example (examples/02_finetune_new_observation_action.py):
the pretrained tiny reference model with its wrist camera removed, a new `proprio` LowdimObsTokenizer, a new
L1 action head with another horizon, window 1, one camera; new parts freshly initialised, everything else
merged from the pretrained weights; saved in Octo's save_pretrained layout and loaded with load_pretrained.
"""

import json
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization, traverse_util

import envs
from harness.policies import as_policy
from harness.policies.octo import step_key
from harness.conventions import CheckpointConventions
from harness.octo import load_pretrained
from harness.octo.diffusion import make_schedule, sample
from harness.octo.normalization import normalize
from harness.policy import EnvMismatchError, InferenceRequest, PolicyConfig, TaskPrompt
from harness.rollout import rollout
from harness.run import Protocol, execute
from harness.outputs.writers import OutputOptions
from tests.octo.recorded import load_expected, observations, task, threefry_flag

STEPS = 3
HORIZON = 3
SIZE = 64  # the tiny model's primary camera size
PROPRIO_STATS = {  # plausible Lift proprio statistics (eef position, xyz Euler, fingers)
    "mean": [-0.1, 0.0, 1.0, 3.0, 0.0, 0.0, 0.02, -0.02],
    "std": [0.1, 0.1, 0.1, 0.5, 0.2, 0.2, 0.01, 0.01],
    "p01": [-0.3, -0.2, 0.8, -3.1, -0.4, -0.4, 0.0, -0.04],
    "p99": [0.1, 0.2, 1.2, 3.1, 0.4, 0.4, 0.04, 0.0],
    "mask": [True] * 7 + [False],
}
CONVENTIONS = CheckpointConventions(
    env={"action_space": "robosuite", "image_convention": "opengl", "cameras": {"image_primary": ["agentview", SIZE]}},
    policy={"dataset_key": "robosuite_ft", "proprio_normalization": "normal", "execution": "receding_horizon",
            "receding_steps": 2},
)


def build_finetune_checkpoint(dst: Path, fixtures_dir: Path, *, action_dim: int = 7, lowdim_key: str = "proprio",
                              save: bool = True) -> Path:
    src = fixtures_dir / "tiny"
    config = json.loads((src / "config.json").read_text())
    model = config["model"]
    del model["observation_tokenizers"]["wrist"]
    model["observation_tokenizers"]["proprio"] = {
        "module": "octo.model.components.tokenizers", "name": "LowdimObsTokenizer", "args": [],
        "kwargs": {"n_bins": 256, "bin_type": "normal", "low": -2.0, "high": 2.0, "obs_keys": [lowdim_key]}}
    model["heads"]["action"] = {
        "module": "octo.model.components.action_heads", "name": "L1ActionHead", "args": [],
        "kwargs": {"readout_key": "readout_action", "action_horizon": HORIZON, "action_dim": action_dim}}
    config["window_size"] = 1
    dst.mkdir(parents=True)
    (dst / "config.json").write_text(json.dumps(config))
    shutil.copytree(src / "t5-tiny", dst / "t5-tiny")

    batch = serialization.msgpack_restore((src / "example_batch.msgpack").read_bytes())
    obs = batch["observation"]
    last = lambda x: x[:, -1:]  # noqa: E731  window 1
    batch["observation"] = {
        "image_primary": last(obs["image_primary"]), "timestep": last(obs["timestep"]),
        "timestep_pad_mask": last(obs["timestep_pad_mask"]),
        "pad_mask_dict": {"image_primary": last(obs["pad_mask_dict"]["image_primary"]),
                          "timestep": last(obs["pad_mask_dict"]["timestep"])},
        lowdim_key: np.zeros((1, 1, 8), np.float32),
    }
    del batch["task"]["image_wrist"], batch["task"]["pad_mask_dict"]["image_wrist"]
    batch["action"] = np.zeros((1, 1, HORIZON, action_dim), np.float32)
    batch["action_pad_mask"] = np.ones((1, 1, HORIZON, action_dim), bool)
    (dst / "example_batch.msgpack").write_bytes(serialization.msgpack_serialize(batch))

    action = {"mean": [0.0] * action_dim, "std": [0.3] * (action_dim - 1) + [1.0],
              "p01": [-1.0] * action_dim, "p99": [1.0] * action_dim, "mask": [True] * (action_dim - 1) + [False]}
    stats = {"robosuite_ft": {"action": action, lowdim_key: PROPRIO_STATS, "num_transitions": 1000, "num_trajectories": 10}}
    (dst / "dataset_statistics.json").write_text(json.dumps(stats))
    if not save:
        return dst

    # new parts freshly initialised, everything else from the pretrained model (as Octo's merge_params)
    fresh = traverse_util.flatten_dict(load_pretrained(f"random:{dst}").params)
    pretrained = traverse_util.flatten_dict(serialization.msgpack_restore((src / "300000/default/checkpoint").read_bytes()))
    merged = {k: pretrained[k] if k in pretrained and pretrained[k].shape == v.shape else np.asarray(v) for k, v in fresh.items()}
    assert any(k not in pretrained for k in fresh) and sum(k in pretrained for k in fresh) > len(fresh) // 2
    (dst / "5000" / "default").mkdir(parents=True)
    (dst / "5000" / "default" / "checkpoint").write_bytes(serialization.msgpack_serialize(traverse_util.unflatten_dict(merged)))
    CONVENTIONS.write(dst)
    return dst


@pytest.fixture(scope="module")
def finetuned(fixtures_dir, tmp_path_factory):
    return load_pretrained(str(build_finetune_checkpoint(tmp_path_factory.mktemp("ckpt") / "finetuned", fixtures_dir)))


@pytest.fixture(scope="module")
def env():
    options = CONVENTIONS.env_options({"masks": True, "fast_render": True})
    e = envs.make("Lift", options, render_mode="rgb_array")
    yield e
    e.close()


@pytest.mark.slow
def test_finetuned_checkpoint_runs_closed_loop_with_attention_drawn(finetuned, tmp_path):
    assert (finetuned.window_size, finetuned.lowdim_sizes, finetuned.action_horizon) == (1, {"proprio": 8}, HORIZON)
    assert set(finetuned.image_sizes) == {"image_primary"}
    conventions = CheckpointConventions.read(finetuned.checkpoint_dir)  # what the run reads from the checkpoint
    records = []
    protocol = Protocol(model=finetuned.source, tasks=("Lift",), max_steps=STEPS,
                        env=conventions.env_options({"masks": True, "fast_render": True}),
                        policy=conventions.policy_config(), outputs=OutputOptions(png_every=1, video=True))
    summary = execute(protocol, tmp_path, "ft", model=finetuned, progress=False,
                      on_step=lambda job, t, record: records.append(record))
    (row,) = summary.rows
    assert row.status == "ok", row.error
    episode = summary.episode_dir(row)
    assert sorted(p.name for p in episode.glob("step_*_layer_*.png")) == [
        f"step_{t:04d}_layer_{l:02d}.png" for t in range(STEPS) for l in range(2)]
    with np.load(episode / "attention.npz") as z:
        groups = list(z["tokens/group"])
        readout = z["readout_attention"]
        lowdim_share = z["metrics/share/lowdim"]
    # task_language 16, then one timestep: obs_primary 16, obs_proprio 8 (one token per dim), obs_task_language 16, readout 1
    assert len(groups) == 57 and groups.count("obs_proprio") == 8 and readout.shape == (STEPS, 2, 4, 1, 57)
    np.testing.assert_allclose(readout.astype(np.float32).sum(-1), 1.0, atol=5e-3)
    assert lowdim_share.shape == (STEPS, 2) and np.all(lowdim_share > 0)
    lines = [json.loads(line) for line in (episode / "metrics.jsonl").read_text().splitlines()]
    assert len(lines) == STEPS and all(len(line["share"]["lowdim"]) == 2 for line in lines)
    with np.load(episode / "actions.npz") as z:
        assert z["predicted"].shape == (STEPS, HORIZON, 7)
    # receding horizon 2 from the checkpoint's conventions: steps 0 and 2 infer, step 1 reuses the chunk
    assert [r.inferred for r in records] == [True, False, True]

    # opengl convention: the model saw frames upside down; the records (and so the overlays) are upright
    upright = envs.make("Lift", cameras={"image_primary": ("agentview", SIZE)}, fast_render=True, masks=True)
    try:
        obs, info = upright.reset(seed=0)
    finally:
        upright.close()
    np.testing.assert_array_equal(records[0].frames["image_primary"], obs["image_primary"])
    np.testing.assert_array_equal(records[0].masks["image_primary"]["target"], info["masks"]["image_primary"]["target"])
    rows = records[0].tokens.row[records[0].tokens.indices("obs_primary")]
    np.testing.assert_array_equal(rows, np.repeat([3, 2, 1, 0], 4))  # the model's patch row 0 is the upright bottom row


def test_proprio_is_fed_normalised_with_the_checkpoint_statistics(finetuned, env):
    obs, info = env.reset(seed=1)
    config = PolicyConfig(dataset_key="robosuite_ft")
    inference = as_policy(finetuned).inference(config)
    window = {"image_primary": obs["image_primary"][None], "proprio": obs["proprio"][None],
              "timestep_pad_mask": np.ones(1, bool), "pad_mask_dict": {"image_primary": np.ones(1, bool), "proprio": np.ones(1, bool)}}
    (result,) = inference([InferenceRequest(window, TaskPrompt.of(info["instruction"]), seed=3, step=0)])
    by_hand = (obs["proprio"] - np.array(PROPRIO_STATS["mean"])) / (np.array(PROPRIO_STATS["std"]) + 1e-8)
    by_hand[7] = obs["proprio"][7]  # masked dimension stays raw
    batch = jax.tree.map(lambda v: v[None], window)  # the same structure as the policy's (no second compile)
    batch["proprio"] = by_hand[None, None].astype(np.float32)
    np.testing.assert_allclose(normalize(obs["proprio"], PROPRIO_STATS), by_hand, rtol=1e-5, atol=1e-6)
    actions, _ = finetuned.sample_actions(batch, inference.task(TaskPrompt.of(info["instruction"])), step_key(3, 0)[None],
                                          inference.statistics)
    np.testing.assert_allclose(result.chunk, np.asarray(actions[0]), atol=1e-5)
    raw = dict(batch, proprio=obs["proprio"][None, None])  # unnormalised proprio gives other actions
    unnormalised, _ = finetuned.sample_actions(raw, inference.task(TaskPrompt.of(info["instruction"])), step_key(3, 0)[None],
                                               inference.statistics)
    assert np.abs(np.asarray(unnormalised[0]) - result.chunk).max() > 1e-3


def test_action_dimension_mismatch_is_one_line_before_the_episode(fixtures_dir, tmp_path, env):
    six = load_pretrained(f"random:{build_finetune_checkpoint(tmp_path / 'six', fixtures_dir, action_dim=6, save=False)}")
    policy = as_policy(six).closed_loop(PolicyConfig())
    steps = []
    with pytest.raises(EnvMismatchError, match=r"actions are 6-D but the env's 'robosuite' action space takes 7-D") as e:
        rollout(env, policy, steps.append, seed=0, max_steps=2)
    assert "\n" not in str(e.value) and steps == []


@pytest.mark.slow
def test_missing_lowdim_key_is_one_line(fixtures_dir, tmp_path, env):
    model = load_pretrained(f"random:{build_finetune_checkpoint(tmp_path / 'state', fixtures_dir, lowdim_key='state', save=False)}")
    assert model.lowdim_sizes == {"state": 8}
    with pytest.raises(EnvMismatchError, match=r"low-dim observation 'state' \(8-D\) which the env does not give") as e:
        as_policy(model).closed_loop(PolicyConfig()).check_env(env)
    assert "\n" not in str(e.value) and "'proprio'" in str(e.value)


@pytest.mark.slow
def test_octo_1_0_checkpoint_samples_as_the_latest_original_code_by_default(fixtures_dir, tmp_path):
    """A 1.0-format config (pred_horizon) of the tiny model: the default sampler reproduces the recorded actions of
    the latest original code; 'v0.1.0' (one more rng split, the December 2023 behaviour) gives other actions."""
    src = fixtures_dir / "tiny"
    dst = tmp_path / "octo_1_0"
    dst.mkdir()
    config = json.loads((src / "config.json").read_text())
    head = config["model"]["heads"]["action"]["kwargs"]
    head["pred_horizon"] = head.pop("action_horizon")
    (dst / "config.json").write_text(json.dumps(config))
    for name in ("example_batch.msgpack", "dataset_statistics.json", "t5-tiny", "300000"):
        (dst / name).symlink_to(src / name)
    model = load_pretrained(str(dst))
    assert model.config.checkpoint_format == "1.0"
    e = load_expected(fixtures_dir, "tiny")
    expected = e[f"sample/threefry_partitionable_{threefry_flag(e)}/actions_normalized"]  # (2, 4, 7)
    latest, _ = model.sample_actions(observations(e), task(e), jax.random.PRNGKey(0), capture_attention=False)
    np.testing.assert_allclose(np.asarray(latest), expected, atol=1e-4)

    # both samplers on the recorded readout embedding (no second transformer compile)
    embedding = e["transformer_outputs/readout_action/tokens"].mean(axis=-2)  # (2, 2, 64)
    score = lambda x, t: model.predict_eps(embedding, x, jnp.broadcast_to(t, (*x.shape[:-1], 1)))  # noqa: E731
    run = lambda sampler: np.asarray(sample(score, jax.random.PRNGKey(0), (2, 2, 28), make_schedule(20), 5.0,  # noqa: E731
                                            jnp.ones((2, 2, 28), bool), sampler)).reshape(2, 2, 4, 7)[:, -1]
    np.testing.assert_allclose(run("latest"), expected, atol=1e-4)
    legacy = run("v0.1.0")
    assert np.abs(legacy - expected).max() > 1e-2  # measured: 0.077 (the "5e-2 apart")
    with pytest.raises(ValueError, match="sampler"):
        PolicyConfig(sampler="v0.2")
    with pytest.raises(ValueError, match="sampler"):
        model.sample_actions(observations(e), task(e), jax.random.PRNGKey(0), sampler="v0.2")


def test_robosuite_action_space_reaches_the_controller_unchanged(env):
    """The env hands the policy's 7 values to robosuite as they are (clipped to [-1, 1], clipping counted)."""
    env.reset(seed=0)
    inner = env.robosuite_env
    seen, original = [], inner.step
    inner.step = lambda action: (seen.append(np.array(action)), original(action))[1]  # spy; the real step runs
    try:
        *_, info = env.step(np.array([0.5, -0.25, 0.0, 0.0, 0.0, 0.1, 1.0]))
        assert info["action_clipped"] == 0
        *_, info = env.step(np.array([0.5, -0.25, 1.5, 0.0, 0.0, 0.1, -1.0]))
    finally:
        del inner.step
    np.testing.assert_array_equal(seen[0], [0.5, -0.25, 0.0, 0.0, 0.0, 0.1, 1.0])  # gripper +1 = closed, as stored
    np.testing.assert_array_equal(seen[1], [0.5, -0.25, 1.0, 0.0, 0.0, 0.1, -1.0])
    assert info["action_clipped"] == 1


def test_opengl_env_images_masks_and_target_pixels_agree_upside_down(env):
    """In the opengl convention the red cube, its mask and its projected pixel all sit in the flipped frame."""
    obs, info = env.reset(seed=0)
    image = obs["image_primary"].astype(np.float64)
    assert image[:16].mean() > image[-16:].mean() + 30  # the white table is at the TOP of an opengl frame
    target = info["masks"]["image_primary"]["target"]
    row, col = np.round(info["target_pixels"]["image_primary"][0]).astype(int)
    assert target[row, col]
    r, g, b = obs["image_primary"][row, col].astype(int)
    assert r > 80 and r > 1.5 * g and r > 1.5 * b
    np.testing.assert_array_equal(env.render(), obs["image_primary"][::-1])  # render() is for people: upright

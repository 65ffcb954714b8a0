"""Public behaviour of the Octo runtime: compilation, attention capture, token map, tasks, random models."""

from __future__ import annotations

import logging

import jax
import numpy as np
import pytest
from flax import traverse_util

from harness.octo import load_pretrained
from harness.octo.config import OctoConfig
from harness.octo.transformer import attention_rule_mask
from tests.octo.recorded import load_expected, observations, task


@pytest.fixture(scope="module")
def tiny(fixtures_dir):
    return load_pretrained(str(fixtures_dir / "tiny"))


@pytest.fixture(scope="module")
def tiny_goal(fixtures_dir):
    return load_pretrained(str(fixtures_dir / "tiny_goal"))


@pytest.fixture(scope="module")
def inputs(fixtures_dir):
    return {name: load_expected(fixtures_dir, name) for name in ("tiny", "tiny_goal")}


@pytest.mark.slow
def test_no_recompilation_across_steps_and_tasks(fixtures_dir, inputs):
    model = load_pretrained(str(fixtures_dir / "tiny"))  # fresh jit cache
    e = inputs["tiny"]
    obs = observations(e)
    first = model.create_task(texts=["pick up the cube", "open the drawer"])
    second = model.create_task(texts=["stack the blocks", "wipe the table"])
    actions = [model.sample_actions(obs, t, jax.random.PRNGKey(i))[0] for i, t in enumerate([first, first, second])]
    obs_next = {**obs, "image_primary": obs["image_primary"][:, ::-1].copy()}
    actions.append(model.sample_actions(obs_next, second, jax.random.PRNGKey(7))[0])
    assert model.sample_cache_size == 1
    assert not np.allclose(actions[0], actions[1])  # a new key gives a new sample


@pytest.mark.slow
@pytest.mark.parametrize("name", ["tiny", "tiny_goal"])
def test_readout_rows_sum_to_one_and_equal_full_matrix_rows(request, inputs, name):
    model = request.getfixturevalue(name)
    e = inputs[name]
    actions, att = model.sample_actions(observations(e), task(e), jax.random.PRNGKey(3))
    actions_full, att_full = model.sample_actions(observations(e), task(e), jax.random.PRNGKey(3), full_attention=True)
    n = att.tokens.num_keys
    layers, heads = model.config.transformer.num_layers, model.config.transformer.num_heads
    assert att.full is None
    assert att.readout.shape == (2, layers, heads, len(att.tokens.readout_index), n)
    assert att_full.full.shape == (2, layers, heads, n, n)
    np.testing.assert_allclose(np.asarray(att.readout).sum(-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(att.readout, np.asarray(att_full.full)[:, :, :, att.tokens.readout_index, :], atol=1e-6)
    np.testing.assert_allclose(att_full.readout, att.readout, atol=1e-6)
    np.testing.assert_allclose(actions, actions_full, atol=1e-5)
    actions_none, nothing = model.sample_actions(observations(e), task(e), jax.random.PRNGKey(3), capture_attention=False)
    assert nothing is None
    np.testing.assert_allclose(actions_none, actions, atol=1e-5)
    # the missing wrist image (sample 1, t=1) receives exactly zero attention
    wrist_t1 = att.tokens.indices("obs_wrist", timestep=1)
    assert np.all(np.asarray(att.readout)[1][..., wrist_t1] == 0)
    assert np.all(np.asarray(att.readout)[0][..., wrist_t1].sum(-1) > 0)


def test_token_map_of_language_model(tiny):
    tm = tiny.token_map()
    assert tm.num_keys == 90
    expected = ["task_language"] * 16
    for _ in range(2):
        expected += ["obs_primary"] * 16 + ["obs_wrist"] * 4 + ["obs_task_language"] * 16 + ["readout_action"]
    assert list(tm.group) == expected
    assert list(tm.timestep[:17]) == [-1] * 16 + [0] and tm.timestep[-1] == 1
    assert list(tm.readout_index) == [89]
    assert tm.grid("obs_primary") == (4, 4) and tm.grid("obs_wrist") == (2, 2)
    assert tm.camera_group("image_wrist") == "obs_wrist"
    assert (tm.row[16 + 6], tm.col[16 + 6]) == (1, 2)  # row-major patches


def test_token_map_of_goal_model_and_attention_tokens(tiny_goal, inputs):
    e = inputs["tiny_goal"]
    _, att = tiny_goal.sample_actions(observations(e), task(e), jax.random.PRNGKey(0))
    tm = tiny_goal.token_map()
    assert tm.num_keys == 42 and list(tm.readout_index) == [41]
    assert list(tm.indices("obs_wrist", timestep=1)) == [37, 38, 39, 40]
    for key, value in tm.to_arrays().items():
        np.testing.assert_array_equal(att.tokens.to_arrays()[key], value)


@pytest.mark.slow
def test_released_architecture_token_map(caplog):
    with caplog.at_level(logging.WARNING):
        model = load_pretrained("random:octo-small-1.5")
    assert model.is_random and "RANDOM MODEL" in caplog.text
    assert model.source == "random:octo-small-1.5"
    assert model.image_sizes == {"image_primary": (256, 256), "image_wrist": (128, 128)}
    assert (model.window_size, model.action_horizon, model.action_dim) == (2, 4, 7)
    assert model.dataset_statistics == {} and model.unnormalization_statistics(None) is None
    tm = model.token_map()
    assert tm.num_keys == 690
    for group, t, first, last in [("task_language", -1, 0, 15), ("obs_primary", 0, 16, 271), ("obs_wrist", 0, 272, 335),
                                  ("obs_task_language", 0, 336, 351), ("readout_action", 0, 352, 352),
                                  ("obs_primary", 1, 353, 608), ("readout_action", 1, 689, 689)]:
        idx = tm.indices(group, timestep=t)
        assert (idx[0], idx[-1]) == (first, last), group
    assert tm.grid("obs_primary") == (16, 16) and tm.grid("obs_wrist") == (8, 8)


def test_create_task_encodes_language_once_and_it_is_reused(tiny, inputs):
    e = inputs["tiny"]
    t = tiny.create_task(texts=["pick up the red cube", "open the drawer"])
    assert t["language_encoding"].shape == (2, 16, 32)
    assert t["pad_mask_dict"]["language_instruction"].tolist() == [True, True]
    assert t["pad_mask_dict"]["image_primary"].tolist() == [False, False]
    assert not t["image_primary"].any() and t["image_primary"].shape == (2, 64, 64, 3)
    np.testing.assert_array_equal(t["language_encoding"], tiny.encode_language(t["language_instruction"]))
    cached, _ = tiny.sample_actions(observations(e), t, jax.random.PRNGKey(1))
    without = {k: v for k, v in t.items() if k != "language_encoding"}
    recomputed, _ = tiny.sample_actions(observations(e), without, jax.random.PRNGKey(1))
    np.testing.assert_allclose(cached, recomputed, atol=1e-6)


def test_create_task_from_goal_images(tiny_goal, inputs):
    goals = {"image_primary": inputs["tiny_goal"]["input/task/image_primary"]}
    t = tiny_goal.create_task(goals=goals)
    assert "language_instruction" not in t and "language_encoding" not in t
    assert t["pad_mask_dict"]["image_primary"].tolist() == [True, True]
    assert t["pad_mask_dict"]["image_wrist"].tolist() == [False, False] and not t["image_wrist"].any()


def test_same_seed_gives_identical_actions_and_attention(tiny, inputs):
    e = inputs["tiny"]
    a1, att1 = tiny.sample_actions(observations(e), task(e), jax.random.PRNGKey(11))
    a2, att2 = tiny.sample_actions(observations(e), task(e), jax.random.PRNGKey(11))
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(att1.readout, att2.readout)


@pytest.mark.slow
def test_bounds_unnormalisation_and_shorter_statistics(tiny, inputs):
    e = inputs["tiny"]
    key = jax.random.PRNGKey(2)
    normalised, _ = tiny.sample_actions(observations(e), task(e), key)
    stats = tiny.unnormalization_statistics("bridge_dataset")
    bounds, _ = tiny.sample_actions(observations(e), task(e), key, stats, normalization_type="bounds")
    a = np.asarray(normalised)
    want = np.where(stats["mask"], (a + 1) * (stats["p99"] - stats["p01"]) / 2 + stats["p01"], a)
    np.testing.assert_allclose(bounds, want, rtol=1e-5, atol=1e-6)
    six = {k: np.asarray(v)[:6] for k, v in stats.items()}
    short, _ = tiny.sample_actions(observations(e), task(e), key, six)
    assert short.shape == (2, 4, 6)


@pytest.mark.slow
def test_random_model_from_a_checkpoint_folder_is_deterministic(fixtures_dir, tiny, inputs):
    first = load_pretrained(f"random:{fixtures_dir / 'tiny'}")
    second = load_pretrained(f"random:{fixtures_dir / 'tiny'}")
    assert first.is_random and not tiny.is_random
    flat = traverse_util.flatten_dict(first.params)
    real = traverse_util.flatten_dict(tiny.params)
    assert {k: v.shape for k, v in flat.items()} == {k: v.shape for k, v in real.items()}
    assert all(np.array_equal(v, traverse_util.flatten_dict(second.params)[k]) for k, v in flat.items())
    assert not np.allclose(flat[("heads_action", "diffusion_model", "reverse_network", "Dense_1", "kernel")],
                           real[("heads_action", "diffusion_model", "reverse_network", "Dense_1", "kernel")])
    e = inputs["tiny"]
    actions, att = first.sample_actions(observations(e), first.create_task(texts=["a", "b"]), jax.random.PRNGKey(0))
    assert np.isfinite(np.asarray(actions)).all()
    np.testing.assert_allclose(np.asarray(att.readout).sum(-1), 1.0, atol=1e-5)


def test_december_2023_attention_labelling():
    """use_correct_attention=False (Octo 1.0) labels each group's first token with the previous group."""
    prefix, steps = [("task_language", 2)], [("obs_primary", 2), ("readout_action", 1)]
    correct = attention_rule_mask(prefix, steps, window=1, use_correct_attention=True).astype(int)
    old = attention_rule_mask(prefix, steps, window=1, use_correct_attention=False).astype(int)
    np.testing.assert_array_equal(correct, [[1, 1, 0, 0, 0], [1, 1, 0, 0, 0], [1, 1, 1, 1, 0], [1, 1, 1, 1, 0], [1, 1, 1, 1, 1]])
    # the readout (key 4) is labelled obs_primary, so observation tokens attend to it
    np.testing.assert_array_equal(old, [[1, 1, 0, 0, 0], [1, 1, 0, 0, 0], [1, 1, 1, 1, 1], [1, 1, 1, 1, 1], [1, 1, 1, 1, 1]])


def test_causal_mask_across_timesteps():
    mask = attention_rule_mask([], [("obs_primary", 1), ("readout_action", 1)], window=2)
    # keys: t0 obs, t0 readout, t1 obs, t1 readout
    np.testing.assert_array_equal(mask.astype(int), [[1, 0, 0, 0], [1, 1, 0, 0], [1, 0, 1, 0], [1, 1, 1, 1]])


def test_octo_1_0_config_shims(fixtures_dir):
    import json

    config = json.loads((fixtures_dir / "tiny" / "config.json").read_text())
    model = config["model"]
    del model["use_correct_attention"], model["repeat_task_tokens"]
    head = model["heads"]["action"]["kwargs"]
    head["pred_horizon"] = head.pop("action_horizon")
    parsed = OctoConfig.from_dict(config)
    assert not parsed.use_correct_attention and not parsed.repeat_task_tokens
    assert parsed.action_head.action_horizon == 4 and parsed.checkpoint_format == "1.0"
    assert OctoConfig.from_json(fixtures_dir / "tiny" / "config.json").checkpoint_format == "1.5"


def test_orbax_layout_checkpoint_loads(fixtures_dir, tiny, tmp_path):
    """A checkpoint without the msgpack `checkpoint` file (orbax OCDBT layout) restores through orbax."""
    import shutil

    import orbax.checkpoint as ocp

    dst = tmp_path / "orbax"
    shutil.copytree(fixtures_dir / "tiny", dst, ignore=shutil.ignore_patterns("300000"))
    ocp.PyTreeCheckpointer().save(str((dst / "7" / "default").resolve()), jax.tree.map(np.asarray, tiny.params))
    assert not (dst / "7" / "default" / "checkpoint").exists()
    restored = load_pretrained(str(dst))
    flat, ref = traverse_util.flatten_dict(restored.params), traverse_util.flatten_dict(tiny.params)
    assert flat.keys() == ref.keys() and all(np.array_equal(flat[k], ref[k]) for k in ref)


@pytest.mark.slow
def test_continuous_map_head_and_proprio_tokenizer(fixtures_dir, tmp_path):
    """An L1 head with MAP pooling and a LowdimObsTokenizer: parsed, initialised and sampled (random weights)."""
    import json

    from flax import serialization

    config = json.loads((fixtures_dir / "tiny_goal" / "config.json").read_text())
    config["model"]["observation_tokenizers"]["proprio"] = {
        "module": "octo.model.components.tokenizers", "name": "LowdimObsTokenizer", "args": [],
        "kwargs": {"obs_keys": ["proprio"], "n_bins": 256, "bin_type": "normal", "low": -2.0, "high": 2.0}}
    config["model"]["heads"]["action"] = {
        "module": "octo.model.components.action_heads", "name": "L1ActionHead", "args": [],
        "kwargs": {"readout_key": "readout_action", "action_horizon": 4, "action_dim": 7}}
    (tmp_path / "config.json").write_text(json.dumps(config))
    batch = serialization.msgpack_restore((fixtures_dir / "tiny_goal" / "example_batch.msgpack").read_bytes())
    batch["observation"]["proprio"] = np.zeros((1, 2, 8), np.float32)
    (tmp_path / "example_batch.msgpack").write_bytes(serialization.msgpack_serialize(batch))
    model = load_pretrained(f"random:{tmp_path}")
    assert set(model.params["heads_action"]) == {"map_head", "mean_proj"}
    assert model.params["octo_transformer"]["obs_proprio_projection"]["kernel"].shape == (1, 64)
    assert model.params["octo_transformer"]["obs_proprio_pos_embedding"].shape == (1, 10, 8, 64)
    obs = {"image_primary": np.zeros((1, 2, 64, 64, 3), np.uint8), "image_wrist": np.zeros((1, 2, 32, 32, 3), np.uint8),
           "proprio": np.linspace(-1, 1, 16, dtype=np.float32).reshape(1, 2, 8), "timestep_pad_mask": np.ones((1, 2), bool)}
    goals = {"image_primary": np.zeros((1, 64, 64, 3), np.uint8)}
    actions, att = model.sample_actions(obs, model.create_task(goals=goals), jax.random.PRNGKey(0))
    assert actions.shape == (1, 4, 7) and np.all(np.abs(np.asarray(actions)) <= 5.0)
    assert list(att.tokens.indices("obs_proprio", timestep=1)) == list(range(49, 57))  # 29 tokens per step: 16 + 4 + 8 + 1
    np.testing.assert_allclose(np.asarray(att.readout).sum(-1), 1.0, atol=1e-5)

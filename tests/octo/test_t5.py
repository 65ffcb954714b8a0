"""T5 encoder: equivalence with the original Octo (HF Flax T5) outputs, parameter trees, config resolution."""

import json

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from harness.octo.t5 import (
    T5_BASE,
    T5Config,
    T5Encoder,
    UnknownT5EncoderError,
    masked_attention_weights,
    relative_position_buckets,
    rms_norm,
    t5_config_for,
)


def _paths_and_shapes(tree) -> dict[str, tuple[int, ...]]:
    flat = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {"/".join(str(k.key) for k in path): tuple(leaf.shape) for path, leaf in flat}


@pytest.fixture(scope="module")
def tiny_t5(fixtures_dir):
    blob = (fixtures_dir / "tiny" / "300000" / "default" / "checkpoint").read_bytes()
    params = flax.serialization.msgpack_restore(blob)["octo_transformer"]["task_tokenizers_language"]["hf_model"]
    expected = np.load(fixtures_dir / "tiny_expected.npz")
    config = t5_config_for("t5-tiny", fixtures_dir / "tiny")
    return config, params, expected


def test_tiny_encoder_matches_reference_outputs(tiny_t5):
    config, params, expected = tiny_t5
    input_ids = expected["input/task/language_instruction/input_ids"]  # (2, 16)
    attention_mask = expected["input/task/language_instruction/attention_mask"]  # (2, 16)
    want = expected["tokenizer/task_language/tokens"]  # (2, 16, 32)
    got = np.asarray(jax.jit(T5Encoder(config).apply)({"params": params}, input_ids, attention_mask))
    assert got.shape == want.shape == (2, 16, 32) and got.dtype == np.float32
    max_abs = float(np.abs(got - want).max())
    print(f"T5 tiny max abs error vs reference: {max_abs:.3e}")
    assert max_abs <= 1e-5


def test_init_tree_equals_tiny_checkpoint_subtree(tiny_t5):
    config, params, _ = tiny_t5
    ids = jnp.zeros((1, 16), jnp.int32)
    shapes = jax.eval_shape(T5Encoder(config).init, jax.random.PRNGKey(0), ids, ids)["params"]
    assert _paths_and_shapes(shapes) == _paths_and_shapes(params)


def test_t5_base_tree_matches_released_param_tree(fixtures_dir):
    prefix = "octo_transformer/task_tokenizers_language/hf_model/"
    ids = jnp.zeros((1, 16), jnp.int32)
    got = _paths_and_shapes(jax.eval_shape(T5Encoder(T5_BASE).init, jax.random.PRNGKey(0), ids, ids)["params"])
    for model in ("octo-small-1.5", "octo-base-1.5"):
        released = json.loads((fixtures_dir / "released" / f"{model}.param_tree.json").read_text())["params"]
        want = {k[len(prefix):]: tuple(v["shape"]) for k, v in released.items() if k.startswith(prefix)}
        assert len(want) == 12 * 8 + 3  # 12 blocks x 8 leaves, plus shared, final norm, block-0 position bias
        assert got == want, model
    assert sum(int(np.prod(s)) for s in got.values()) == 109628544  # n_params_t5_encoder of the released trees


def test_t5_base_config_from_released_hf_config(fixtures_dir):
    hf = json.loads((fixtures_dir / "released" / "t5-base.config.json").read_text())
    assert T5Config.from_hf_dict(hf) == T5_BASE
    assert t5_config_for("t5-base", None) is T5_BASE
    assert t5_config_for("google-t5/t5-base", "/nonexistent") is T5_BASE


@pytest.mark.parametrize("name", ["bert-base-uncased", "t5-huge", "/abs/t5-tiny", "../tiny/t5-tiny"])
def test_unknown_encoder_name_is_one_clear_error(fixtures_dir, name):
    with pytest.raises(UnknownT5EncoderError, match="unknown T5 encoder .*supported: google-t5/t5-base, t5-base") as e:
        t5_config_for(name, fixtures_dir / "tiny")
    assert "\n" not in str(e.value)
    assert isinstance(e.value, ValueError)


def test_relative_name_without_checkpoint_dir_is_an_error():
    with pytest.raises(UnknownT5EncoderError, match="t5-tiny"):
        t5_config_for("t5-tiny", None)


def test_unsupported_feed_forward_is_an_error():
    with pytest.raises(ValueError, match="feed_forward_proj 'swiglu'"):
        T5Config(vocab_size=10, d_model=4, d_kv=2, d_ff=8, num_layers=1, num_heads=2, feed_forward_proj="swiglu")


def test_relative_position_buckets_hand_values():
    buckets = relative_position_buckets(300, num_buckets=32, max_distance=128)  # (q, k)
    assert buckets.shape == (300, 300) and buckets.dtype == np.int32
    q = 150
    # key before the query (k - q < 0): buckets 0..15; after: 16..31
    cases = {0: 0, -1: 1, -7: 7, -8: 8, -15: 9, -16: 10, -127: 15, -128: 15, -149: 15,
             1: 17, 7: 23, 8: 24, 16: 26, 32: 28, 64: 30, 127: 31, 149: 31}
    for rel, want in cases.items():
        assert buckets[q, q + rel] == want, rel
    assert (buckets == relative_position_buckets(300, 32, 128)).all()  # deterministic, pure


def test_rms_norm_hand_computation():
    x = jnp.array([[3.0, 4.0], [0.0, 2.0]])  # (rows, dim)
    weight = jnp.array([1.0, 2.0])
    got = np.asarray(rms_norm(x, weight, eps=0.0))
    want = np.array([[3 / np.sqrt(12.5), 8 / np.sqrt(12.5)], [0.0, 4 / np.sqrt(2.0)]])
    np.testing.assert_allclose(got, want, rtol=1e-6)


def test_masked_attention_gives_zero_weight_to_masked_keys():
    logits = jnp.array(np.random.default_rng(0).normal(size=(1, 2, 3, 3)), jnp.float32)  # (batch, heads, q, k)
    weights = np.asarray(masked_attention_weights(logits, jnp.array([[True, False, True]])))
    assert (weights[..., 1] == 0).all()
    np.testing.assert_allclose(weights.sum(-1), 1.0, rtol=1e-6)


def test_padding_tokens_do_not_change_real_token_outputs(tiny_t5):
    config, params, expected = tiny_t5
    ids = np.array(expected["input/task/language_instruction/input_ids"])
    mask = expected["input/task/language_instruction/attention_mask"]
    apply = jax.jit(T5Encoder(config).apply)
    before = np.asarray(apply({"params": params}, ids, mask))
    ids[mask == 0] = 42  # garbage in the padded positions
    after = np.asarray(apply({"params": params}, ids, mask))
    real = mask.astype(bool)
    np.testing.assert_allclose(after[real], before[real], atol=1e-6)
    assert not np.allclose(after[~real], before[~real])


@pytest.mark.slow
def test_gated_gelu_feed_forward_parameter_names():
    config = T5Config(vocab_size=10, d_model=8, d_kv=2, d_ff=16, num_layers=2, num_heads=4,
                      feed_forward_proj="gated-gelu")
    ids = jnp.ones((1, 5), jnp.int32)
    variables = T5Encoder(config).init(jax.random.PRNGKey(0), ids, ids)
    got = _paths_and_shapes(variables["params"])
    assert got["encoder/block/1/layer/1/DenseReluDense/wi_0/kernel"] == (8, 16)
    assert got["encoder/block/1/layer/1/DenseReluDense/wi_1/kernel"] == (8, 16)
    assert "encoder/block/1/layer/1/DenseReluDense/wi/kernel" not in got
    out = T5Encoder(config).apply(variables, ids, ids)
    assert out.shape == (1, 5, 8) and bool(jnp.isfinite(out).all())

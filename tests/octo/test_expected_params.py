"""`loading.expected_params` (one transformer block and two T5 blocks traced, the rest copied) is exactly the tree
that tracing `init_params` through every block gives: the same paths, shapes, dtypes and key order, for the
released architectures and the committed checkpoints."""

from __future__ import annotations

import jax
import pytest
from flax import traverse_util

from harness.octo import checkpoint, loading, presets
from harness.octo.config import OctoConfig
from harness.octo.network import init_params

REPO = __import__("pathlib").Path(__file__).resolve().parents[2]


def _full(config, t5, shapes):
    return jax.eval_shape(lambda key: init_params(key, config, t5_config=t5, **shapes), jax.random.PRNGKey(0))


def _listing(tree) -> list:
    return [(path, tuple(leaf.shape), str(leaf.dtype)) for path, leaf in traverse_util.flatten_dict(tree).items()]


def _same(config, t5, shapes):
    full, fast = _full(config, t5, shapes), loading.expected_params(config, t5, shapes)
    assert _listing(fast) == _listing(full)  # paths in the same order, shapes and dtypes
    assert jax.tree.structure(fast) == jax.tree.structure(full)


@pytest.mark.parametrize("name", ["octo-small-1.5", "octo-base-1.5"])
def test_presets(name):
    config = OctoConfig.from_dict(presets.preset_config(name))
    t5 = loading._t5_config(config, None)
    example = loading._synthetic_example_batch(config, presets.IMAGE_SIZES, presets.WINDOW_SIZE)
    _same(config, t5, loading._input_shapes(config, example))


@pytest.mark.parametrize("folder", ["tests/fixtures/octo-reference/tiny", "models/octo-reference-robosuite",
                                    "models/octo-reference-libero-object"])
def test_checkpoints(folder):
    ckpt = REPO / folder
    config = OctoConfig.from_json(ckpt / "config.json")
    t5 = loading._t5_config(config, ckpt)
    _same(config, t5, loading._input_shapes(config, checkpoint.read_example_batch(ckpt)))


@pytest.mark.parametrize("layers,t5_layers", [(1, 1), (3, 3), (2, 5)])
def test_layer_counts(layers, t5_layers):
    """One block, and more blocks than are traced, in both stacks (block 0 of T5 alone holds the position bias)."""
    import dataclasses

    ckpt = REPO / "tests/fixtures/octo-reference/tiny"
    config = OctoConfig.from_json(ckpt / "config.json")
    config = dataclasses.replace(config, transformer=dataclasses.replace(config.transformer, num_layers=layers))
    t5 = dataclasses.replace(loading._t5_config(config, ckpt), num_layers=t5_layers)
    _same(config, t5, loading._input_shapes(config, checkpoint.read_example_batch(ckpt)))

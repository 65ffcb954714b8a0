"""The released octo-small-1.5 / octo-base-1.5 architectures, built abstractly (jax.eval_shape), have
exactly the parameter paths and shapes of the released checkpoints (fixture released/*.param_tree.json)."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from flax import traverse_util

from harness.octo import presets
from harness.octo.config import OctoConfig
from harness.octo.network import init_params
from harness.octo.t5 import t5_config_for


def _abstract_tree(config: OctoConfig) -> dict[str, tuple[tuple[int, ...], str]]:
    t5 = t5_config_for(config.language.encoder, None)
    shapes = jax.eval_shape(
        lambda key: init_params(key, config, presets.IMAGE_SIZES, presets.WINDOW_SIZE, t5, None, presets.LANGUAGE_TOKENS),
        jax.random.PRNGKey(0),
    )
    return {"/".join(k): (tuple(v.shape), str(v.dtype)) for k, v in traverse_util.flatten_dict(shapes).items()}


@pytest.mark.parametrize("name", ["octo-small-1.5", "octo-base-1.5"])
def test_preset_matches_released_parameter_tree(fixtures_dir, name):
    released = json.loads((fixtures_dir / "released" / f"{name}.param_tree.json").read_text())
    expected = {path: (tuple(v["shape"]), v["dtype"]) for path, v in released["params"].items()}
    built = _abstract_tree(OctoConfig.from_dict(presets.preset_config(name)))
    assert sorted(set(expected) - set(built)) == []  # every released parameter is built
    assert sorted(set(built) - set(expected)) == []  # nothing extra is built
    wrong = {p: (built[p], expected[p]) for p in expected if built[p] != expected[p]}
    assert wrong == {}
    assert sum(int(np.prod(s)) for s, _ in built.values()) == released["n_params_total"]


@pytest.mark.parametrize("name", ["octo-small-1.5", "octo-base-1.5"])
def test_released_config_parses_to_the_preset(fixtures_dir, name):
    """The embedded preset equals what the released config.json (annotations aside) parses to."""
    released = json.loads((fixtures_dir / "released" / f"{name}.config.json").read_text())
    released = {k: v for k, v in released.items() if not k.startswith("_")}
    assert OctoConfig.from_dict(released) == OctoConfig.from_dict(presets.preset_config(name))

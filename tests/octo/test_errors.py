"""Each user mistake gets one clear line that names the fix (and an OctoError subclass)."""

from __future__ import annotations

import json
import shutil

import huggingface_hub.constants
import jax
import numpy as np
import pytest

from harness.octo import OctoError, load_pretrained
from harness.octo.errors import (
    CheckpointNotFoundError,
    ConfigError,
    CorruptCheckpointError,
    HubUnavailableError,
    InputError,
    ParamTreeMismatchError,
    UnknownDatasetKeyError,
    UnsupportedModuleError,
)
from tests.octo.recorded import load_expected, observations, task


def _one_line(err: pytest.ExceptionInfo) -> str:
    text = str(err.value)
    assert "\n" not in text and text, text
    assert isinstance(err.value, OctoError)
    return text


@pytest.fixture
def tiny_copy(fixtures_dir, tmp_path):
    dst = tmp_path / "tiny"
    shutil.copytree(fixtures_dir / "tiny", dst)
    for p in dst.rglob("*"):
        p.chmod(0o644 if p.is_file() else 0o755)
    dst.chmod(0o755)
    return dst


def _edit_config(path, edit):
    config = json.loads((path / "config.json").read_text())
    edit(config["model"])
    (path / "config.json").write_text(json.dumps(config))


@pytest.fixture(scope="module")
def tiny(fixtures_dir):
    return load_pretrained(str(fixtures_dir / "tiny"))


def test_missing_checkpoint_directory(tmp_path):
    with pytest.raises(CheckpointNotFoundError) as err:
        load_pretrained(str(tmp_path / "nowhere"))
    assert isinstance(err.value, FileNotFoundError)
    assert "does not exist" in _one_line(err) and "hf://" in str(err.value)


def test_missing_config_json(tiny_copy):
    (tiny_copy / "config.json").unlink()
    with pytest.raises(CheckpointNotFoundError) as err:
        load_pretrained(str(tiny_copy))
    assert "config.json" in _one_line(err)


def test_no_step_folder_and_unknown_step(tiny_copy):
    with pytest.raises(CheckpointNotFoundError) as err:
        load_pretrained(str(tiny_copy), step=5)
    assert "available steps: [300000]" in _one_line(err)
    shutil.rmtree(tiny_copy / "300000")
    with pytest.raises(CheckpointNotFoundError) as err:
        load_pretrained(str(tiny_copy))
    assert "no <step>/" in _one_line(err)


def test_truncated_checkpoint_file(tiny_copy):
    blob = tiny_copy / "300000" / "default" / "checkpoint"
    blob.write_bytes(blob.read_bytes()[: blob.stat().st_size // 2])
    with pytest.raises(CorruptCheckpointError) as err:
        load_pretrained(str(tiny_copy))
    assert isinstance(err.value, ValueError)
    text = _one_line(err)
    assert "corrupt or truncated" in text and str(blob) in text


def test_unknown_module_is_named(tiny_copy):
    def edit(model):
        model["observation_tokenizers"]["wrist"]["kwargs"]["encoder"]["name"] = "ResNet26FILM"

    _edit_config(tiny_copy, edit)
    with pytest.raises(UnsupportedModuleError) as err:
        load_pretrained(str(tiny_copy))
    text = _one_line(err)
    assert "ResNet26FILM" in text and "observation_tokenizers.wrist" in text and "SmallStem16" in text


def test_unsupported_option_is_named(tiny_copy):
    _edit_config(tiny_copy, lambda m: m["observation_tokenizers"]["primary"]["kwargs"].update(use_token_learner=True))
    with pytest.raises(UnsupportedModuleError) as err:
        load_pretrained(str(tiny_copy))
    assert "use_token_learner" in _one_line(err)


def test_mismatched_parameter_tree_lists_paths_and_shapes(tiny_copy):
    _edit_config(tiny_copy, lambda m: m.update(token_embedding_size=32))
    with pytest.raises(ParamTreeMismatchError) as err:
        load_pretrained(str(tiny_copy))
    text = _one_line(err)
    assert "expected (" in text and "found (" in text and "more)" in text
    assert "octo_transformer/" in text


def test_extra_layer_reported_as_missing_in_checkpoint(tiny_copy):
    """The layer count is checked against the parameter files before the model is traced (issue 44)."""
    _edit_config(tiny_copy, lambda m: m["transformer_kwargs"].update(num_layers=3))
    with pytest.raises(ConfigError) as err:
        load_pretrained(str(tiny_copy))
    assert "num_layers 3" in _one_line(err) and "2 encoder blocks" in str(err.value)


def test_unknown_dataset_key_lists_available(tiny):
    with pytest.raises(UnknownDatasetKeyError) as err:
        tiny.unnormalization_statistics("fractal20220817_data")
    assert "bridge_dataset" in _one_line(err)
    assert tiny.unnormalization_statistics(None) is None


def test_offline_hub_without_cache_names_the_fix(tmp_path, monkeypatch):
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)  # never touch the network
    with pytest.raises(HubUnavailableError) as err:
        load_pretrained("hf://rail-berkeley/octo-small-1.5", cache_dir=tmp_path / "empty-hf-cache")
    assert isinstance(err.value, FileNotFoundError)
    text = _one_line(err)
    assert "HF_HUB_OFFLINE" in text and "local checkpoint path" in text


def test_wrong_image_shape_names_expected_shape(tiny, fixtures_dir):
    e = load_expected(fixtures_dir, "tiny")
    obs = observations(e)
    obs["image_primary"] = np.zeros((2, 2, 256, 256, 3), np.uint8)
    with pytest.raises(InputError) as err:
        tiny.sample_actions(obs, task(e), jax.random.PRNGKey(0))
    assert "(batch, window, 64, 64, 3) uint8" in _one_line(err)
    obs["image_primary"] = np.zeros((2, 2, 64, 64, 3), np.float32)
    with pytest.raises(InputError):
        tiny.sample_actions(obs, task(e), jax.random.PRNGKey(0))


def test_unknown_goal_key_and_texts_for_goal_model(tiny, fixtures_dir):
    with pytest.raises(InputError) as err:
        tiny.create_task(goals={"image_third": np.zeros((1, 64, 64, 3), np.uint8)})
    assert "image_primary" in _one_line(err)
    goal_model = load_pretrained(str(fixtures_dir / "tiny_goal"))
    with pytest.raises(InputError) as err:
        goal_model.create_task(texts=["pick up the cube"])
    assert "goals=" in _one_line(err)


def test_unknown_random_preset(tmp_path):
    with pytest.raises(CheckpointNotFoundError) as err:
        load_pretrained("random:octo-huge-9")
    assert "random:octo-small-1.5" in _one_line(err)

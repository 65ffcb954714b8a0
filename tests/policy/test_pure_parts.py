"""Pure parts of the policy wrapper: temporal ensembling, frame resizing, config validation."""

import numpy as np
import pytest

from harness.policy import PolicyConfig, ensemble, resize_frame


def test_ensemble_averages_the_actions_each_chunk_predicted_for_now():
    # chunk i (oldest first) was predicted len-1-i steps ago, so its entry [len-1-i] is the action for now.
    horizon, dim = 4, 7
    chunks = [np.full((horizon, dim), np.nan, np.float32) for _ in range(3)]
    chunks[0][2] = 1.0  # predicted 2 steps ago
    chunks[1][1] = 2.0  # 1 step ago
    chunks[2][0] = 6.0  # now
    np.testing.assert_allclose(ensemble(chunks, 0.0), np.full(dim, 3.0))
    w = np.exp(-0.5 * np.arange(3))
    np.testing.assert_allclose(ensemble(chunks, 0.5), np.full(dim, (w @ [1.0, 2.0, 6.0]) / w.sum()), rtol=1e-6)


def test_ensemble_of_one_chunk_is_its_first_action():
    chunk = np.arange(28, dtype=np.float32).reshape(4, 7)
    np.testing.assert_array_equal(ensemble([chunk], 0.0), chunk[0])


def test_resize_keeps_orientation_and_size():
    frame = np.zeros((256, 256, 3), np.uint8)
    frame[:128, :, 0] = 255  # top half red
    small = resize_frame(frame, (64, 64))
    assert small.shape == (64, 64, 3) and small.dtype == np.uint8
    assert small[:30, :, 0].min() > 200 and small[34:, :, 0].max() < 50
    assert resize_frame(frame, (256, 256)) is frame


def test_policy_config_rejects_unknown_execution():
    with pytest.raises(ValueError, match="temporal_ensemble"):
        PolicyConfig(execution="fancy")
    assert PolicyConfig(execution="receding_horizon", receding_steps=3).describe() == "receding_horizon:3"

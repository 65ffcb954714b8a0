"""Attention analysis on hand-made inputs whose answers are known."""

import numpy as np
import pytest

from harness.measures import attention as A
from harness.octo.tokens import build_token_map


def tiny_tokens():
    # 0..15 task_language; t0: 16..31 primary, 32..35 wrist, 36..51 lang, 52 readout; t1: 53..68, 69..72, 73..88, 89
    return build_token_map(
        [("task_language", 16)],
        [("obs_primary", 16), ("obs_wrist", 4), ("obs_task_language", 16), ("readout_action", 1)],
        2,
        (("obs_primary", "image_primary", 4, 4), ("obs_wrist", "image_wrist", 2, 2)),
    )


def released_tokens():
    return build_token_map(
        [("task_language", 16)],
        [("obs_primary", 256), ("obs_wrist", 64), ("obs_task_language", 16), ("readout_action", 1)],
        2,
        (("obs_primary", "image_primary", 16, 16), ("obs_wrist", "image_wrist", 8, 8)),
    )


def test_camera_maps_pick_the_camera_keys_row_major():
    tokens = tiny_tokens()
    rows = np.arange(90, dtype=float)
    np.testing.assert_array_equal(A.camera_maps(rows, tokens, "image_primary"), np.arange(53, 69).reshape(4, 4))
    np.testing.assert_array_equal(A.camera_maps(rows, tokens, "image_wrist"), [[69, 70], [71, 72]])
    np.testing.assert_array_equal(A.camera_maps(rows, tokens, "image_primary", timestep=0), np.arange(16, 32).reshape(4, 4))
    # leading axes are kept: (layers, heads, readouts, keys) -> (layers, heads, readouts, 2, 2)
    batch = np.broadcast_to(rows, (3, 4, 1, 90))
    assert A.camera_maps(batch, tokens, "image_wrist").shape == (3, 4, 1, 2, 2)


def test_camera_maps_released_layout():
    tokens = released_tokens()
    assert tokens.num_keys == 690
    rows = np.arange(690, dtype=float)
    np.testing.assert_array_equal(A.camera_maps(rows, tokens, "image_primary"), np.arange(353, 609).reshape(16, 16))
    np.testing.assert_array_equal(A.camera_maps(rows, tokens, "image_wrist"), np.arange(609, 673).reshape(8, 8))
    np.testing.assert_array_equal(A.camera_maps(rows, tokens, "image_wrist", 0), np.arange(272, 336).reshape(8, 8))


def test_camera_maps_reject_wrong_inputs():
    tokens = tiny_tokens()
    with pytest.raises(ValueError, match="keys"):
        A.camera_maps(np.zeros(89), tokens, "image_primary")
    with pytest.raises(ValueError, match="window"):
        A.camera_maps(np.zeros(90), tokens, "image_primary", timestep=2)
    with pytest.raises(KeyError):
        A.camera_maps(np.zeros(90), tokens, "image_side")


def test_fuse_heads():
    x = np.array([[[1.0, 4.0]], [[3.0, 0.0]]])  # (heads 2, q 1, k 2)
    np.testing.assert_array_equal(A.fuse_heads(x, "mean"), [[2.0, 2.0]])
    np.testing.assert_array_equal(A.fuse_heads(x, "max"), [[3.0, 4.0]])
    np.testing.assert_array_equal(A.fuse_heads(x, "min"), [[1.0, 0.0]])
    np.testing.assert_array_equal(A.fuse_heads(x, "max", axis=0), [[3.0, 4.0]])
    with pytest.raises(ValueError, match="mean"):
        A.fuse_heads(x, "median")


def test_attention_rollout_known_answer():
    a1 = np.array([[1.0, 0.0], [0.5, 0.5]])
    a2 = np.array([[0.5, 0.5], [0.0, 1.0]])
    full = np.stack([a1, a2])[:, None]  # (layers 2, heads 1, 2, 2)
    # no residual: A2 @ A1 (layer order matters: A1 @ A2 would be [[.5, .5], [.25, .75]])
    np.testing.assert_allclose(A.attention_rollout(full, residual=False), [[0.75, 0.25], [0.5, 0.5]])
    # residual: (0.5 A + 0.5 I) per layer
    np.testing.assert_allclose(A.attention_rollout(full), [[0.8125, 0.1875], [0.25, 0.75]])


def test_attention_rollout_fuses_heads_and_renormalises():
    h0 = np.array([[1.0, 0.0], [0.0, 1.0]])
    h1 = np.array([[0.0, 1.0], [1.0, 0.0]])
    full = np.stack([h0, h1])[None]  # (layers 1, heads 2, 2, 2)
    np.testing.assert_allclose(A.attention_rollout(full, residual=False), [[0.5, 0.5], [0.5, 0.5]])
    np.testing.assert_allclose(A.attention_rollout(full, residual=False, head_fusion="max"), [[0.5, 0.5], [0.5, 0.5]])
    rng = np.random.default_rng(0)
    full = rng.dirichlet(np.ones(6), size=(3, 2, 6))  # (layers, heads, q, k)
    np.testing.assert_allclose(A.attention_rollout(full).sum(-1), 1.0)
    with pytest.raises(ValueError, match="square"):
        A.attention_rollout(np.ones((2, 2, 1, 6)))


def test_rollout_readout_rows_tiny_layout():
    tokens = tiny_tokens()
    full = np.broadcast_to(np.eye(90), (2, 4, 90, 90))
    rows = A.rollout_readout_rows(full, tokens)
    assert rows.shape == (1, 90)
    np.testing.assert_array_equal(rows[0], np.eye(90)[89])


def test_rollout_readout_rows_equal_full_rollout_rows():
    tokens = tiny_tokens()
    full = np.random.default_rng(5).dirichlet(np.ones(90), size=(3, 4, 90))  # (layers, heads, q, k)
    for residual in (True, False):
        expected = A.attention_rollout(full, residual=residual)[tokens.readout_index]
        np.testing.assert_allclose(A.rollout_readout_rows(full, tokens, residual=residual), expected, atol=1e-12)


def test_modality_and_timestep_shares():
    tokens = tiny_tokens()
    row = np.zeros(90)
    row[20] = 0.5  # t0 primary
    row[70] = 0.2  # t1 wrist
    row[3] = 0.15  # prefix language
    row[80] = 0.05  # t1 repeated language
    row[52] = 0.1  # t0 readout
    shares = A.modality_shares(row, tokens)
    assert set(shares) == {"primary", "wrist", "language", "readout"}
    np.testing.assert_allclose([shares[k] for k in ("primary", "wrist", "language", "readout")], [0.5, 0.2, 0.2, 0.1])
    steps = A.timestep_shares(row, tokens)
    np.testing.assert_allclose([steps["prefix"], steps["earlier"], steps["current"]], [0.15, 0.6, 0.25])
    split = A.modality_shares(row, tokens, per_timestep=True)
    assert set(split) == {"primary/earlier", "primary/current", "wrist/earlier", "wrist/current", "language/prefix",
                          "language/earlier", "language/current", "readout/earlier", "readout/current"}
    np.testing.assert_allclose([split["primary/earlier"], split["wrist/current"], split["language/prefix"],
                                split["language/current"], split["readout/earlier"]], [0.5, 0.2, 0.15, 0.05, 0.1])
    np.testing.assert_allclose(sum(split.values()), 1.0)
    # unnormalised rows give the same fractions; batches keep their shape
    np.testing.assert_allclose(A.modality_shares(row * 3, tokens)["primary"], 0.5)
    rows = np.random.default_rng(1).dirichlet(np.ones(90), size=(2, 3))
    total = sum(A.modality_shares(rows, tokens).values())
    assert total.shape == (2, 3)
    np.testing.assert_allclose(total, 1.0)


def test_modality_shares_other_groups():
    tokens = build_token_map(
        [("task_language", 2)],
        [("obs_primary", 4), ("obs_proprio", 1), ("readout_action", 1)],
        1,
        (("obs_primary", "image_primary", 2, 2),),
    )
    row = np.array([0.1, 0.1, 0.2, 0.0, 0.0, 0.0, 0.4, 0.2])
    shares = A.modality_shares(row, tokens)
    assert set(shares) == {"primary", "lowdim", "language", "readout"}
    np.testing.assert_allclose(shares["lowdim"], 0.4)
    np.testing.assert_allclose(sum(shares.values()), 1.0)


def test_upsample_map_is_patch_constant():
    onehot = np.zeros((4, 4))
    onehot[1, 2] = 1
    up = A.upsample_map(onehot, 64, 64)
    expected = np.zeros((64, 64))
    expected[16:32, 32:48] = 1
    np.testing.assert_array_equal(up, expected)
    # non-divisible: 3 patches over 10 pixels -> 4, 3, 3 pixels
    up = A.upsample_map(np.arange(3.0)[None], 1, 10)
    np.testing.assert_array_equal(up[0], [0, 0, 0, 0, 1, 1, 1, 2, 2, 2])


def test_mask_mass_known_answers():
    onehot = np.zeros((4, 4))
    onehot[1, 2] = 1
    mask = np.zeros((64, 64), bool)
    mask[16:32, 32:48] = True
    assert A.mask_mass(onehot, mask) == pytest.approx(1.0)
    assert A.mask_mass(onehot * 7, mask) == pytest.approx(1.0)  # normalised over the camera
    half = np.zeros((64, 64), bool)
    half[16:32, 32:40] = True
    assert A.mask_mass(onehot, half) == pytest.approx(0.5)
    assert A.mask_mass(onehot, ~mask) == pytest.approx(0.0)
    # uniform attention gets exactly the area fraction (chance level)
    assert A.mask_mass(np.ones((4, 4)), half) == pytest.approx(A.mask_area_fraction(half))
    assert A.mask_area_fraction(half) == pytest.approx(128 / 4096)
    # non-divisible sizes: patch (0, 0) of a 3x3 grid covers 4x4 pixels of a 10x10 mask
    corner = np.zeros((3, 3))
    corner[0, 0] = 1
    pixel = np.zeros((10, 10), bool)
    pixel[0, 0] = True
    assert A.mask_mass(corner, pixel) == pytest.approx(1 / 16)
    assert np.isnan(A.mask_mass(np.zeros((4, 4)), mask))
    with pytest.raises(ValueError, match="smaller"):
        A.mask_mass(onehot, np.ones((2, 2), bool))


def test_entropy():
    np.testing.assert_allclose(A.entropy(np.full(4, 0.25)), np.log(4))
    np.testing.assert_allclose(A.entropy(np.array([0.5, 0.5, 0.0, 0.0])), np.log(2))
    np.testing.assert_allclose(A.entropy(np.array([0.0, 1.0])), 0.0)
    np.testing.assert_allclose(A.entropy(np.array([2.0, 2.0])), np.log(2))
    np.testing.assert_allclose(A.entropy(np.array([[1.0, 0.0], [0.5, 0.5]]), axis=0), [np.log(3) - 2 / 3 * np.log(2), 0.0])
    np.testing.assert_allclose(A.entropy(np.zeros(3)), 0.0)


def test_step_metrics_tiny_layout():
    tokens = tiny_tokens()
    rng = np.random.default_rng(2)
    attn = rng.dirichlet(np.ones(90), size=(2, 4, 1))  # (layers, heads, readouts, keys)
    target = np.zeros((64, 64), bool)
    target[0:16, 0:16] = True  # exactly patch (0, 0) of the 4x4 primary grid
    m = A.step_metrics(attn, tokens, {"image_primary": {"target": target}, "image_side": {"target": target}})
    shares = [m[f"share/{k}"] for k in ("primary", "wrist", "language", "readout")]
    assert all(s.shape == (2,) for s in shares)
    np.testing.assert_allclose(sum(shares), 1.0)
    np.testing.assert_allclose(m["timestep_share/prefix"] + m["timestep_share/earlier"] + m["timestep_share/current"], 1.0)
    # hand computation: head-mean primary map at t1, its (0, 0) patch over its total
    mean = attn.mean(axis=(1, 2))
    primary = mean[:, 53:69]
    np.testing.assert_allclose(m["mask_mass/image_primary/target"], primary[:, 0] / primary.sum(-1))
    assert float(m["mask_area/image_primary/target"]) == pytest.approx(1 / 16)
    np.testing.assert_allclose(m["share/primary"], mean[:, np.r_[16:32, 53:69]].sum(-1))
    expected_entropy = -(attn * np.log(attn)).sum(-1).mean(axis=(1, 2))
    np.testing.assert_allclose(m["entropy"], expected_entropy)
    assert not any(k.startswith("mask_mass/image_side") for k in m)


def test_mask_patch_fraction_is_each_patchs_share_of_mask_pixels_for_any_size():
    """Brute force over the pixels each patch covers (proportional coordinates, as upsample_map), for sizes that do
    and do not divide the grid; the cached patch ids of one size never leak into another."""
    rng = np.random.default_rng(3)
    for height, width, rows, cols in ((128, 128, 8, 8), (100, 77, 8, 8), (64, 64, 4, 4), (130, 128, 8, 8)):
        mask = rng.random((height, width)) < rng.random()
        ry, cx = A.patch_index(height, rows), A.patch_index(width, cols)
        expected = np.array([[mask[np.ix_(ry == r, cx == c)].mean() for c in range(cols)] for r in range(rows)])
        assert np.array_equal(A.mask_patch_fraction(mask, rows, cols), expected), (height, width)

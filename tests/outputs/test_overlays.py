"""Overlays put each patch's colour on exactly the pixels of that patch, in the frame's orientation."""

import numpy as np
import pytest

from harness.measures.attention import upsample_map
from harness.outputs.overlays import (
    BOX,
    attribution_panel,
    colormap_lut,
    heatmap_overlay,
    heatmap_overlays,
    layer_panel,
    mask_bbox,
    resize_nearest,
    video_frame,
)


def onehot(rows, cols, r, c):
    m = np.zeros((rows, cols))
    m[r, c] = 1.0
    return m


@pytest.mark.parametrize("cmap", ["jet", "inferno"])
def test_onehot_lights_exactly_its_patch_tiny_layout(cmap):
    lut = colormap_lut(cmap)
    frame = np.zeros((64, 64, 3), np.uint8)
    out = heatmap_overlay(frame, onehot(4, 4, 1, 2), alpha=1.0, cmap=cmap)
    hot = np.all(out == lut[255], axis=-1)
    cold = np.all(out == lut[0], axis=-1)
    expected = np.zeros((64, 64), bool)
    expected[16:32, 32:48] = True
    np.testing.assert_array_equal(hot, expected)
    np.testing.assert_array_equal(cold, ~expected)


def test_onehot_lights_exactly_its_patch_released_layout():
    lut = colormap_lut("viridis")
    frame = np.full((256, 256, 3), 100, np.uint8)
    out = heatmap_overlay(frame, onehot(16, 16, 5, 11), alpha=0.5)
    blend = lambda colour: ((100 * 128 + colour.astype(int) * 128 + 128) >> 8).astype(np.uint8)  # noqa: E731
    expected = np.zeros((256, 256), bool)
    expected[80:96, 176:192] = True
    np.testing.assert_array_equal(np.all(out == blend(lut[255]), axis=-1), expected)
    np.testing.assert_array_equal(np.all(out == blend(lut[0]), axis=-1), ~expected)
    # wrist: 128 px frame, 8x8 grid -> 16 px patches
    out = heatmap_overlay(np.zeros((128, 128, 3), np.uint8), onehot(8, 8, 7, 0), alpha=1.0)
    assert np.all(out[112:, :16] == lut[255]) and np.all(out[:112] == lut[0]) and np.all(out[:, 16:] == lut[0])


def test_overlay_keeps_orientation_and_matches_upsample_for_uneven_sizes():
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (100, 70, 3), dtype=np.uint8)
    m = rng.random((16, 16))
    # alpha 0 returns the frame untouched (no flips, no resampling)
    np.testing.assert_array_equal(heatmap_overlay(frame, m, alpha=0.0), frame)
    # alpha 1 with a non-divisible size: the colour of each pixel is that of upsample_map's patch
    out = heatmap_overlay(frame, m, 0.0, 1.0, alpha=1.0)
    index = np.clip(np.rint(upsample_map(m, 100, 70) * 255), 0, 255).astype(int)
    np.testing.assert_array_equal(out, colormap_lut("viridis")[index])


def test_overlays_batch_equals_single_and_ranges_clip():
    rng = np.random.default_rng(1)
    frame = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    maps = rng.random((3, 4, 4))
    batch = heatmap_overlays(frame, maps, 0.2, 0.8)
    for i in range(3):
        np.testing.assert_array_equal(batch[i], heatmap_overlay(frame, maps[i], 0.2, 0.8))
    flat = heatmap_overlay(np.zeros((8, 8, 3), np.uint8), np.full((2, 2), 5.0), alpha=1.0)  # degenerate range
    assert np.all(flat == colormap_lut("viridis")[0])
    with pytest.raises(ValueError, match="colormap"):
        heatmap_overlay(frame, maps[0], cmap="no-such-map")
    with pytest.raises(ValueError, match="uint8"):
        heatmap_overlay(frame.astype(float), maps[0])


def test_mask_bbox_and_resize():
    mask = np.zeros((10, 12), bool)
    mask[2:5, 3:9] = True
    assert mask_bbox(mask) == (2, 3, 5, 9)
    assert mask_bbox(np.zeros((4, 4), bool)) is None
    assert mask_bbox(None) is None
    image = np.arange(4).reshape(2, 2)
    np.testing.assert_array_equal(resize_nearest(image, 4, 4), np.repeat(np.repeat(image, 2, 0), 2, 1))


def test_layer_panel_draws_every_head_and_the_mean():
    lut = colormap_lut("viridis")
    frames = {"image_primary": np.zeros((64, 64, 3), np.uint8), "image_wrist": np.zeros((32, 32, 3), np.uint8)}
    maps = {
        "image_primary": np.stack([onehot(4, 4, 1, 2)] * 3),  # (heads 3, 4, 4)
        "image_wrist": np.stack([onehot(2, 2, 0, 0), onehot(2, 2, 0, 0), onehot(2, 2, 1, 1)]),
    }
    caption = {"task": "Lift", "step": 7, "layer": 1, "note": "RANDOM WEIGHTS"}
    panel = layer_panel(frames, maps, caption, ranges={"image_primary": (0, 1), "image_wrist": (0, 1)}, alpha=1.0)
    assert panel.dtype == np.uint8 and panel.ndim == 3
    hot = np.all(panel == lut[255], axis=-1).sum()
    # frames shown at 128 px (x2 and x4): primary patch 32x32 in 3 heads + mean; wrist patch 64x64 in 3 heads
    # (the wrist mean peaks at 2/3, not hottest); each colour bar has one hottest row of 12 pixels
    assert hot == 4 * 32 * 32 + 3 * 64 * 64 + 2 * 12
    assert not np.any(np.all(panel == BOX, axis=-1))
    boxed = layer_panel(frames, maps, caption, boxes={"image_primary": (10, 10, 20, 20)})
    assert np.any(np.all(boxed == BOX, axis=-1))
    assert boxed.shape == panel.shape  # constant size, whatever the data
    with pytest.raises(ValueError, match="no frame"):
        layer_panel({"image_primary": frames["image_primary"]}, maps, caption)


def test_attribution_panel_colours_each_method_over_its_own_range():
    lut = colormap_lut("viridis")
    frames = {"image_primary": np.zeros((64, 64, 3), np.uint8), "image_wrist": np.zeros((32, 32, 3), np.uint8)}
    maps = {  # units differ by orders of magnitude: each cell still shows its own hottest patch
        "attention:2": {"image_primary": onehot(4, 4, 0, 0) * 1e-3, "image_wrist": onehot(2, 2, 1, 1) * 1e-3},
        "saliency": {"image_primary": onehot(4, 4, 3, 3) * 50.0, "image_wrist": onehot(2, 2, 0, 1) * 50.0},
        "occlusion": {"image_primary": onehot(4, 4, 2, 1)},  # no wrist map: that cell is the bare frame
    }
    panel = attribution_panel(frames, maps, {"task": "Lift", "step": 3}, alpha=1.0)
    hot = np.all(panel == lut[255], axis=-1).sum()
    # primary at 128 px (x2): one 32x32 patch per method (3); wrist at 128 px (x4): one 64x64 patch in 2 methods;
    # each colour bar has one hottest row of 12 pixels
    assert hot == 3 * 32 * 32 + 2 * 64 * 64 + 2 * 12
    cold = np.all(panel == lut[0], axis=-1).sum()
    assert cold == 3 * 15 * 32 * 32 + 2 * 3 * 64 * 64 + 2 * 12  # the bare wrist frame (black) is not colour 0
    with pytest.raises(ValueError, match="one \\(rows, cols\\) grid"):
        attribution_panel(frames, {"saliency": {"image_primary": np.zeros((2, 4, 4))}}, {})
    with pytest.raises(ValueError, match="at least one method"):
        attribution_panel(frames, {}, {})


def test_video_frame_layout():
    rng = np.random.default_rng(3)
    frame = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
    overlay = heatmap_overlay(frame, rng.random((4, 4)))
    strip = rng.random((12, 4, 4))
    out = video_frame(frame, overlay, strip, ["step 3", "action [0.1 0.2]", "success False"], box=(0, 0, 8, 8))
    assert out.shape[0] % 16 == 0 and out.shape[1] % 16 == 0
    np.testing.assert_array_equal(out[:256, :256], resize_nearest(frame, 256, 256))  # camera frame, upright, x4
    other = video_frame(frame, overlay, rng.random((12, 4, 4)), ["a much longer caption " * 10])
    assert other.shape == out.shape

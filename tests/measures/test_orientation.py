"""The orientation measures on hand-made pictures whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from harness.measures.orientation import MEASURES, area_resize, correlation, is_flat, orientation_scores


def _picture(seed: int = 0, size: int = 64) -> np.ndarray:
    """(size, size, 3) uint8: a dark band at the top, a bright block lower left, smooth noise: no symmetry."""
    rng = np.random.default_rng(seed)
    image = np.full((size, size), 120.0)
    image[: size // 4] = 30
    image[size // 2: size - 8, 4: size // 3] = 230
    image += area_resize(rng.normal(0, 40, (size, size)), size // 8).repeat(8, 0).repeat(8, 1)
    return np.repeat(np.clip(image, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def test_area_resize_averages_blocks():
    image = np.arange(16, dtype=float).reshape(4, 4)
    assert area_resize(image, 2).tolist() == [[2.5, 4.5], [10.5, 12.5]]


def test_correlation_of_a_vector_with_itself_its_negative_and_a_constant():
    a = np.array([1.0, 2.0, 4.0, 8.0])
    assert correlation(a, a) == pytest.approx(1.0)
    assert correlation(a, -a) == pytest.approx(-1.0)
    assert correlation(a, np.ones(4)) == 0.0


def test_flat_frames_hold_no_picture():
    assert is_flat(np.zeros((8, 8, 3), np.uint8)) and is_flat(np.full((8, 8, 3), 90, np.uint8))
    assert not is_flat(_picture())


@pytest.mark.parametrize("measure", MEASURES)
def test_each_orientation_is_found_at_another_size(measure):
    upright = _picture()
    small = area_resize(upright[..., 0], 32).astype(np.uint8)
    small = np.repeat(small[..., None], 3, axis=2)
    for example, want in ((small, "upright"), (small[::-1], "opengl"), (small[:, ::-1], "rot180")):
        scores = orientation_scores(example, upright, measure)
        assert max(scores, key=scores.get) == want
        assert scores[want] > 0.9

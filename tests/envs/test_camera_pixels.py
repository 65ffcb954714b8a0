"""envs.camera.image_pixels: the projected pixel of a point in each image convention is where that convention's
image holds the point's pixel (both simulators' envs use it for `target_pixels`)."""

import numpy as np
import pytest

from envs.camera import image_pixels, project_points
from envs.options import IMAGE_CONVENTIONS, to_convention

CAM_POS = np.zeros(3)
CAM_XMAT = np.eye(3)  # looks along world -z, +y up


@pytest.mark.parametrize("convention", IMAGE_CONVENTIONS)
def test_a_projected_point_lands_on_its_pixel_in_every_convention(convention):
    size = 16
    point = np.array([[0.12, 0.3, -1.0]])  # right of and above the optical axis
    row, col = np.round(project_points(point, CAM_POS, CAM_XMAT, 60.0, size, size)[0]).astype(int)
    assert row < size // 2 - 1 and col > size // 2  # upright: above and to the right of the centre
    upright = np.zeros((size, size), bool)
    upright[row, col] = True
    expected = np.argwhere(to_convention(upright, convention))[0]
    got = image_pixels(point, CAM_POS, CAM_XMAT, 60.0, size, convention)
    assert got.dtype == np.float32 and got.shape == (1, 2)
    assert np.round(got[0]).astype(int).tolist() == expected.tolist()


def test_points_behind_the_camera_stay_nan():
    got = image_pixels(np.array([[0.0, 0.0, 1.0]]), CAM_POS, CAM_XMAT, 45.0, 8, "rot180")
    assert np.isnan(got).all()

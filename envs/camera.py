"""Pinhole projection of world points into the upright camera images, as pure numpy.

A MuJoCo camera looks along its local -z axis with +y up and a vertical field of view `fovy`; square
pixels, principal point at the image centre. Pixel coordinates returned here are (row, col) of the
upright image (row 0 at the top) in *index* units: the centre of pixel (i, j) is at (i, j), so
`np.round(...).astype(int)` gives the pixel that contains the point. `image_pixels` turns them into the
pixels of an image in an env's image convention (envs.options), for both simulators' envs.
"""

from __future__ import annotations

import numpy as np


def intrinsic_matrix(fovy_degrees: float, height: int, width: int) -> np.ndarray:
    """(3, 3) intrinsics mapping camera (x right, y down, z forward) to continuous pixel (u, v)."""
    focal = 0.5 * height / np.tan(np.deg2rad(fovy_degrees) / 2.0)
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def world_to_camera(cam_pos: np.ndarray, cam_xmat: np.ndarray) -> np.ndarray:
    """(3, 4) extrinsics: world point -> camera frame with x right, y down, z forward (OpenCV axes).

    cam_pos: (3,) camera position in the world; cam_xmat: (3, 3) or (9,) MuJoCo camera frame (columns:
    camera x right, y up, z backward, in world coordinates).
    """
    rotation = np.asarray(cam_xmat, dtype=np.float64).reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])  # (3, 3) cam->world
    world_to_cam = rotation.T
    return np.concatenate([world_to_cam, -(world_to_cam @ np.asarray(cam_pos, dtype=np.float64))[:, None]], axis=1)


def project_points(points: np.ndarray, cam_pos: np.ndarray, cam_xmat: np.ndarray, fovy_degrees: float, height: int, width: int) -> np.ndarray:
    """(n, 3) world points -> (n, 2) float (row, col) in index units; points behind the camera give NaN."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    homogeneous = np.concatenate([points, np.ones((len(points), 1))], axis=1)  # (n, 4)
    in_camera = homogeneous @ world_to_camera(cam_pos, cam_xmat).T  # (n, 3)
    pixels = in_camera @ intrinsic_matrix(fovy_degrees, height, width).T  # (n, 3)
    depth = pixels[:, 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.where(depth > 0, pixels[:, :2] / depth, np.nan)  # (n, 2) continuous (u, v)
    return np.stack([uv[:, 1] - 0.5, uv[:, 0] - 0.5], axis=1)


def image_pixels(points: np.ndarray, cam_pos: np.ndarray, cam_xmat: np.ndarray, fovy_degrees: float, size: int,
                 convention: str) -> np.ndarray:
    """(n, 3) world points -> (n, 2) float32 (row, col) in a square `size` image of `convention` (envs.options:
    "upright"; "opengl" rows bottom first; "rot180" also columns flipped, as the env returns its images)."""
    rc = project_points(points, cam_pos, cam_xmat, fovy_degrees, size, size)
    if convention == "opengl":
        rc[:, 0] = (size - 1) - rc[:, 0]
    elif convention == "rot180":
        rc[:, 1] = (size - 1) - rc[:, 1]
    return rc.astype(np.float32)

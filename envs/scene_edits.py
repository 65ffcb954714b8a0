"""The scene edits the perturbation kinds make (envs.perturbations), without seeds or the kinds' table: rotation maths
(a camera's pose, a light's direction), distractor object models and where they may stand, texture patterns and the
arena's materials, robosuite's placement samplers. Each function takes what was drawn and returns or builds the edit.
"""

from __future__ import annotations

import numpy as np


class PerturbationError(ValueError):
    """A perturbation that cannot be parsed or that a task cannot take (message: one line naming the fix)."""


# ---------------------------------------------------------------------------------------------- rotations

def unit_vector(rng_: np.random.Generator) -> np.ndarray:
    """A (3,) unit vector in a uniformly drawn direction."""
    v = rng_.normal(size=3)
    return v / np.linalg.norm(v)


def axis_angle_quat(axis: np.ndarray, degrees: float) -> np.ndarray:
    """(w, x, y, z) quaternion of a rotation by `degrees` about unit `axis`."""
    half = np.deg2rad(degrees) / 2.0
    return np.concatenate([[np.cos(half)], np.sin(half) * np.asarray(axis, float)])


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (w, x, y, z) quaternions."""
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def perturbed_camera(pos: np.ndarray, quat: np.ndarray, fovy: float, draw: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """Nominal camera (pos (3,), quat (w, x, y, z), fovy deg) -> the perturbed one (pure; the env and the tests share it)."""
    new_quat = quat_mul(np.asarray(quat, float), axis_angle_quat(draw["axis"], draw["degrees"]))
    return np.asarray(pos, float) + draw["offset"], new_quat / np.linalg.norm(new_quat), float(fovy) + draw["fovy_delta"]


def rotate(vector: np.ndarray, axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rodrigues rotation of (3,) `vector` about unit `axis`."""
    t = np.deg2rad(degrees)
    v, k = np.asarray(vector, float), np.asarray(axis, float)
    return v * np.cos(t) + np.cross(k, v) * np.sin(t) + k * np.dot(k, v) * (1 - np.cos(t))


# ---------------------------------------------------------------------------------------------- distractors

DISTRACTOR_PREFIX = "distractor"
# tasks whose scene has no free surface for distractors (one line before the first episode)
NO_DISTRACTOR_ROOM = {"Door": "the door's arena has no free table surface",
                      "ToolHang": "the stand and the tool fill the table's reachable area"}


def distractor_objects(count: int) -> list:
    """`count` robosuite object models, named distractor0.. (lemon, bottle, blue ball, yellow cylinder, purple box)."""
    from robosuite.models.objects import BallObject, BottleObject, BoxObject, CylinderObject, LemonObject

    makers = (
        lambda n: LemonObject(n),
        lambda n: BottleObject(n),
        lambda n: BallObject(n, size=[0.025], rgba=[0.15, 0.35, 0.9, 1.0]),
        lambda n: CylinderObject(n, size=[0.022, 0.035], rgba=[0.95, 0.8, 0.1, 1.0]),
        lambda n: BoxObject(n, size=[0.024, 0.024, 0.024], rgba=[0.6, 0.25, 0.8, 1.0]),
    )
    return [makers[i % len(makers)](f"{DISTRACTOR_PREFIX}{i}") for i in range(count)]


def class_with_distractors(base, count: int):
    """A subclass of robosuite env class `base` whose model also holds `count` distractor objects (free joints)."""

    def _load_model(self):
        base._load_model(self)
        self._octo_distractors = distractor_objects(count)
        self.model.merge_objects(self._octo_distractors)

    return type(f"{base.__name__}OctoDistractors{count}", (base,), {"_load_model": _load_model})


def distractor_region(env) -> tuple[np.ndarray, np.ndarray, float]:
    """((2,) low xy, (2,) high xy, surface z) where distractors may stand in robosuite env `env`."""
    if hasattr(env, "bin1_pos") and hasattr(env, "bin_size"):  # PickPlace: the start bin
        centre, half = np.asarray(env.bin1_pos, float), np.asarray(env.bin_size[:2], float) / 2 - 0.05
        return centre[:2] - half, centre[:2] + half, float(centre[2])
    offset = getattr(env, "table_offset", None)
    size = getattr(env, "table_full_size", None)
    if offset is None or size is None:
        raise PerturbationError(f"distractors: {type(env).__name__} has no table or bin to place them on; drop distractors")
    half = np.asarray(size[:2], float) / 2 - 0.08
    return np.asarray(offset[:2], float) - half, np.asarray(offset[:2], float) + half, float(offset[2])


def place_distractors(g: np.random.Generator, low: np.ndarray, high: np.ndarray, avoid: np.ndarray, count: int,
                      clearance: float, spacing: float, tries: int = 2000) -> np.ndarray:
    """(count, 2) xy positions in [low, high], >= clearance from every row of `avoid` (k, 2), >= spacing apart."""
    placed: list[np.ndarray] = []
    for _ in range(tries):
        if len(placed) == count:
            break
        xy = g.uniform(low, high)
        if len(avoid) and np.min(np.linalg.norm(avoid - xy, axis=1)) < clearance:
            continue
        if placed and np.min(np.linalg.norm(np.array(placed) - xy, axis=1)) < spacing:
            continue
        placed.append(xy)
    if len(placed) < count:
        raise PerturbationError(f"distractors: no room for {count} objects {clearance:.2f} m from the task's objects "
                                "on this surface; use a lower level")
    return np.array(placed).reshape(count, 2)


# ---------------------------------------------------------------------------------------------- textures and placement

TEXTURE_PATTERNS = ("rgb", "checker", "noise", "gradient")


def texture_pattern(g: np.random.Generator, variation: str, shape: tuple) -> np.ndarray:
    """(h, w, c) float pattern in 0-255: a flat colour, an 8x8 checker, noise of two colours, or a gradient."""
    h, w, c = shape
    a, b = g.uniform(0, 255, size=(2, c))
    if variation == "rgb":
        return np.broadcast_to(a, shape).astype(np.float64)
    if variation == "checker":
        cells = ((np.arange(h)[:, None] * 8 // max(h, 1)) + (np.arange(w)[None, :] * 8 // max(w, 1))) % 2
        return np.where(cells[..., None] == 1, a, b)
    if variation == "noise":
        mask = g.uniform(size=(h, w)) < g.uniform(0.1, 0.9)
        return np.where(mask[..., None], a, b)
    t = np.linspace(0.0, 1.0, h)[:, None, None]
    return np.broadcast_to((1 - t) * a + t * b, shape).astype(np.float64)


def material_texture(model, mat: int) -> int:
    """The RGB texture of material `mat` (-1: none); MuJoCo 3 stores one texture per role."""
    if mat < 0:
        return -1
    ids = np.atleast_1d(np.asarray(model.mat_texid[mat]))
    if ids.size > 1 and ids[1] >= 0:  # mjTEXROLE_RGB
        return int(ids[1])
    valid = ids[ids >= 0]
    return int(valid[0]) if valid.size else -1


def uniform_samplers(sampler) -> list:
    """The UniformRandomSampler leaves of robosuite placement sampler `sampler` (composite samplers unrolled)."""
    if sampler is None:
        return []
    if hasattr(sampler, "samplers"):
        return [leaf for child in sampler.samplers.values() for leaf in uniform_samplers(child)]
    return [sampler] if hasattr(sampler, "x_range") else []

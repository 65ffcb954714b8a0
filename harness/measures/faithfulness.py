"""Faithfulness of attribution maps: does deleting the patches a map ranks highest change the action most?

Pure numpy functions around one evaluation callable (images -> predicted action chunks), named after the
papers they implement:

- `baseline_image` / `delete_patches`: what a deleted patch becomes: the image's per-channel mean ("mean"), a
  Gaussian blur of the image ("blur", sigma = one patch width), or noisy linear imputation from the pixels
  around the deleted region ("impute", `impute`: ROAD, Rong et al. 2022, "A Consistent and Efficient Evaluation
  Strategy for Attribution Methods"): each deleted pixel is the weighted mean of its 8 neighbours (edge
  neighbours 1/6, corner neighbours 1/12) with the kept pixels as the boundary, one sparse linear solve per
  deleted set, plus Gaussian noise. Mean and blur fills give every deleted region a tell-tale flat or smooth
  shape the model may react to (the region's shape leaks the ranking) and leave the training distribution;
  imputation continues the surrounding image instead.
- Deletion and insertion curves (RISE, Petsiuk, Das & Saenko 2018; pixel flipping, Samek et al. 2017) on the
  patch grid, for a policy's continuous action: delete the top-k patches of the ranking (k = 0..n), or insert
  them into the fully deleted image, and measure how far the predicted chunk moves from the one predicted on
  the intact image (`action_change`: RMS over the chunk, normalised units, same rng). The deletion curve
  starts at 0 and ends at change(all deleted); a faithful map makes it rise at once (HIGH AUC). The insertion
  curve starts at change(all deleted) and ends at 0; a faithful map makes it fall at once (LOW AUC). AUC:
  trapezoid over the deleted fraction k/n, in action units. (RISE's probability-retained form, 1 -
  change/change(all), is not used: a camera whose full deletion changes the chunk little makes it explode.)
- MoRF and LeRF (ROAD's names): the deletion curve above removes the Most Relevant patches First; the LeRF
  curve removes the Least Relevant First (a faithful map keeps it low: LOW AUC). The random map's LeRF curve
  is its MoRF curve (a reversed random order is a random order), so both share one control.
- top-k / random-k / bottom-k: the change when the k highest-, randomly- or lowest-ranked patches are deleted.
- `relative_to_random`: a method's AUC over the random map's on the same steps (sums over steps, so 1 = no
  better than random; deletion > 1 and insertion < 1 are better than random) with a percentile bootstrap
  interval over episodes (over steps when there is one episode).

A camera whose whole deletion changes the chunk by less than `MIN_CHANGE` has no curves (the policy does not
use it at this step; nothing to rank): its rows carry `change_all` and NaN elsewhere.
"""

from __future__ import annotations

from typing import Callable, Mapping, Sequence

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
from scipy.ndimage import gaussian_filter

from harness.measures.attention import patch_index

FILLS = ("mean", "blur", "impute")
IMPUTE_NOISE = 2.55  # std of the noise added to imputed pixels, pixel units (1% of the 0..255 range)
IMPUTE_CELLS = 4  # delete_patches imputes on blocks such that a patch spans ~4 blocks a side (speed)
IMPUTE_ANCHOR = 1e-4  # pull of each imputed pixel towards the kept pixels' mean: keeps a fully deleted image solvable
# the 8 neighbours of a pixel and their weights in the imputation (sum 1 in the image's interior)
_NEIGHBOURS = ((-1, 0, 1 / 6), (1, 0, 1 / 6), (0, -1, 1 / 6), (0, 1, 1 / 6),
               (-1, -1, 1 / 12), (-1, 1, 1 / 12), (1, -1, 1 / 12), (1, 1, 1 / 12))
MIN_CHANGE = 1e-6  # normalised action units
TOP_K = (1, 0.1, 0.25)  # patches (int) or fractions of the camera's patches


def baseline_image(image: np.ndarray, fill: str = "mean", rows: int = 1, cols: int = 1) -> np.ndarray:
    """image (H, W, 3) -> (H, W, 3) float32 of deleted content: per-channel mean, or a blur (sigma = a patch)."""
    image = np.asarray(image, np.float32)
    if fill == "mean":
        return np.broadcast_to(image.mean(axis=(0, 1)), image.shape).astype(np.float32)
    if fill == "blur":
        sigma = max(image.shape[0] / rows, image.shape[1] / cols)
        return gaussian_filter(image, sigma=(sigma, sigma, 0), mode="nearest").astype(np.float32)
    if fill == "impute":
        raise ValueError("the impute fill depends on the deleted region: use delete_patches or impute")
    raise ValueError(f"unknown fill {fill!r}; use one of {', '.join(FILLS)}")


def impute(image: np.ndarray, deleted: np.ndarray, noise: float = IMPUTE_NOISE, rng=None, factor: int = 1) -> np.ndarray:
    """Noisy linear imputation (ROAD): image (H, W, C), deleted (H, W) bool -> (H, W, C) float32, 0..255.

    The deleted pixels u solve, per channel, (s_u + e) x_u - sum_{v deleted} w_uv x_v = sum_{v kept} w_uv x_v + e m,
    where w are the neighbour weights (_NEIGHBOURS, those inside the image), s_u their sum, m the kept pixels'
    mean (the image's when nothing is kept) and e = IMPUTE_ANCHOR: each deleted pixel is (almost exactly) the
    weighted mean of its neighbours, kept ones fixed. The matrix is symmetric and strictly diagonally dominant,
    so every connected deleted region has one solution; each is solved alone (one sparse LU, C right-hand sides).
    factor > 1 (dividing H and W): the system is solved on the image averaged over factor x factor blocks (a
    block is deleted when any of its pixels is) and the solution upsampled bilinearly into the deleted pixels:
    factor^2 fewer unknowns. N(0, noise) is then added to the deleted pixels (rng: a numpy Generator or seed;
    noise 0: none). A constant image comes back unchanged when noise is 0.
    """
    image = np.asarray(image, np.float64)
    deleted = np.asarray(deleted, bool)
    h, w, c = image.shape
    if deleted.shape != (h, w):
        raise ValueError(f"deleted mask {deleted.shape} does not match the image {(h, w)}")
    if factor < 1 or h % factor or w % factor:
        raise ValueError(f"imputation factor {factor} must divide the image size {(h, w)}")
    out = image.copy()
    if not deleted.any():
        return out.astype(np.float32)
    if factor > 1:
        coarse = image.reshape(h // factor, factor, w // factor, factor, c).mean(axis=(1, 3))
        cells = deleted.reshape(h // factor, factor, w // factor, factor).any(axis=(1, 3))
        solved = _solve_imputation(coarse, cells)
        smooth = _upsample(solved, factor)
        out[deleted] = smooth[deleted]
    else:
        out = _solve_imputation(image, deleted)
    if noise > 0:
        generator = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        out[deleted] += generator.normal(0.0, noise, (int(deleted.sum()), c))
    return np.clip(out, 0.0, 255.0).astype(np.float32)


def _solve_imputation(image: np.ndarray, deleted: np.ndarray) -> np.ndarray:
    """image (H, W, C) float64, deleted (H, W) bool -> (H, W, C) float64: the deleted pixels solved (see `impute`).

    One sparse system for every deleted region at once (its matrix is block diagonal over the 8-connected regions,
    which the LU's fill-reducing ordering keeps apart)."""
    h, w, c = image.shape
    kept = ~deleted
    anchor = image[kept].mean(axis=0) if kept.any() else image.reshape(-1, c).mean(axis=0)  # (C,)
    flat = image.reshape(-1, c)
    pixels = np.flatnonzero(deleted)  # (u,)
    u = pixels.size
    index = np.full(h * w, -1, np.int64)
    index[pixels] = np.arange(u)
    ys, xs = np.divmod(pixels, w)
    diagonal = np.full(u, IMPUTE_ANCHOR)
    rhs = np.broadcast_to(IMPUTE_ANCHOR * anchor, (u, c)).copy()
    rows, cols, values = [np.arange(u)], [np.arange(u)], []
    for dy, dx, weight in _NEIGHBOURS:
        ny, nx = ys + dy, xs + dx
        inside = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
        diagonal[inside] += weight
        neighbour = np.where(inside, ny * w + nx, 0)
        other = np.where(inside, index[neighbour], -1)
        unknown = inside & (other >= 0)
        rows.append(np.flatnonzero(unknown))
        cols.append(other[unknown])
        values.append(np.full(int(unknown.sum()), -weight))
        known = inside & (other < 0)
        rhs[known] += weight * flat[neighbour[known]]
    matrix = scipy.sparse.csc_matrix((np.concatenate([diagonal, *values]),
                                      (np.concatenate(rows), np.concatenate(cols))), shape=(u, u))
    out = image.copy()
    out.reshape(-1, c)[pixels] = scipy.sparse.linalg.splu(matrix, permc_spec="MMD_AT_PLUS_A").solve(rhs)
    return out


def _upsample(coarse: np.ndarray, factor: int) -> np.ndarray:
    """(h, w, C) -> (h*factor, w*factor, C) bilinear, pixel centres aligned (edges held)."""
    def axis_weights(n: int):
        position = (np.arange(n * factor) + 0.5) / factor - 0.5
        low = np.clip(np.floor(position).astype(int), 0, n - 1)
        high = np.clip(low + 1, 0, n - 1)
        t = np.clip(position - low, 0.0, 1.0)[:, None]
        return low, high, t

    ly, hy, ty = axis_weights(coarse.shape[0])
    rows = coarse[ly] * (1 - ty[..., None]) + coarse[hy] * ty[..., None]
    lx, hx, tx = axis_weights(coarse.shape[1])
    return rows[:, lx] * (1 - tx) + rows[:, hx] * tx


def impute_factor(height: int, width: int, rows: int, cols: int, cells: int = IMPUTE_CELLS) -> int:
    """The block size `delete_patches` imputes at: patches of at most ~`cells` blocks a side (a divisor of H, W)."""
    factor = max(1, min(height // rows, width // cols) // cells)
    while height % factor or width % factor:
        factor -= 1
    return factor


def pixel_mask(deleted: np.ndarray, height: int, width: int) -> np.ndarray:
    """deleted (..., rows, cols) bool -> (..., height, width) bool: every pixel of a deleted patch."""
    deleted = np.asarray(deleted, bool)
    ry = patch_index(height, deleted.shape[-2])
    cx = patch_index(width, deleted.shape[-1])
    return deleted[..., ry[:, None], cx[None, :]]


def delete_patches(image: np.ndarray, deleted: np.ndarray, fill: str = "mean", seed=0) -> np.ndarray:
    """image (H, W, 3), deleted (m, rows, cols) bool -> (m, H, W, 3) float32 with the deleted patches filled.

    mean / blur: one baseline image composed in (`compose`); impute: `impute` per deleted set (solved on blocks of
    `impute_factor` pixels: a 16-pixel patch is imputed on 4x4-pixel blocks), with noise drawn from `seed` (an
    int or a sequence of ints) in the order of the sets, so the same call gives the same images.
    """
    deleted = np.asarray(deleted, bool)
    if fill != "impute":
        return compose(image, baseline_image(image, fill, deleted.shape[1], deleted.shape[2]), deleted)
    image = np.asarray(image, np.float32)
    pixels = pixel_mask(deleted, *image.shape[:2])
    factor = impute_factor(*image.shape[:2], *deleted.shape[1:])
    rng = np.random.default_rng(seed)
    return np.stack([impute(image, p, rng=rng, factor=factor) for p in pixels]) if len(pixels) else \
        np.zeros((0, *image.shape), np.float32)


def ranking(scores: np.ndarray) -> np.ndarray:
    """scores (rows, cols) -> (rows*cols,) patch indices, highest score first (ties: lower index first)."""
    flat = np.asarray(scores, np.float64).ravel()
    return np.argsort(-flat, kind="stable")


def first_k(order: np.ndarray, ks: Sequence[int]) -> np.ndarray:
    """order (n,), ks (m,) -> (m, n) bool: the first k patches of the order, for each k."""
    n = len(order)
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    return rank[None, :] < np.asarray(ks)[:, None]


def compose(image: np.ndarray, baseline: np.ndarray, deleted: np.ndarray) -> np.ndarray:
    """image, baseline (H, W, 3); deleted (m, rows, cols) bool -> (m, H, W, 3): baseline inside deleted patches."""
    deleted = np.asarray(deleted, bool)
    pixel = pixel_mask(deleted, *image.shape[:2])  # (m, H, W)
    return np.where(pixel[..., None], baseline[None], image[None]).astype(np.float32)


def action_change(actions: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """actions (..., horizon, dim), reference (horizon, dim) -> (...) RMS difference over the chunk."""
    d = np.asarray(actions, np.float64) - np.asarray(reference, np.float64)
    return np.sqrt((d ** 2).mean(axis=(-2, -1)))


def auc(fractions: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Trapezoid area under values (..., m) over fractions (m,) in [0, 1]."""
    x = np.asarray(fractions, np.float64)
    y = np.asarray(values, np.float64)
    return ((y[..., 1:] + y[..., :-1]) * np.diff(x) / 2).sum(axis=-1)


def curve_points(n: int, max_points: int = 17) -> np.ndarray:
    """The k of a curve over n patches: every k when n + 1 <= max_points, else evenly spaced (0 and n included)."""
    if n + 1 <= max_points:
        return np.arange(n + 1)
    return np.unique(np.round(np.linspace(0, n, max_points)).astype(int))


def k_values(n: int, top_k: Sequence[float] = TOP_K) -> tuple[int, ...]:
    """TOP_K entries -> patch counts in 1..n (ints as given, fractions of n rounded, at least 1), unique."""
    out = []
    for k in top_k:
        count = int(k) if float(k).is_integer() and k >= 1 else max(1, int(round(float(k) * n)))
        if 1 <= count <= n and count not in out:
            out.append(count)
    return tuple(out)


def camera_faithfulness(
    evaluate: Callable[[np.ndarray], np.ndarray],
    image: np.ndarray,
    reference: np.ndarray,
    maps: Mapping[str, np.ndarray],
    *,
    fill: str = "mean",
    random_orders: int = 4,
    seed: int = 0,
    top_k: Sequence[float] = TOP_K,
    max_points: int = 17,
) -> list[dict]:
    """One camera at one step: a row per method with its curves (MoRF deletion, insertion, LeRF), AUCs and
    top/random/bottom-k changes.

    evaluate: images (m, H, W, 3) float32 of this camera's current frame -> (m, horizon, dim) normalised chunks
    (the other inputs held fixed, same rng); image (H, W, 3) the frame as the policy saw it; reference
    (horizon, dim) the chunk predicted from it; maps {method: (rows, cols)}. The random control is the mean
    of `random_orders` random rankings drawn from `seed`; each row carries it (random_deletion_auc, ...).
    """
    first = next(iter(maps.values()))
    rows, cols = first.shape
    n = rows * cols
    topk = k_values(n, top_k)
    ks = _ks_with(n, topk, max_points)  # the curve's k, the top-k counts included
    fractions = ks / n
    rng = np.random.default_rng(seed)
    orders = {name: ranking(m) for name, m in maps.items()}
    controls = [rng.permutation(n) for _ in range(random_orders)]

    deleted = _deleted_sets(list(orders.values()), controls, ks, n)
    distinct, inverse = np.unique(deleted, axis=0, return_inverse=True)  # each distinct set filled, evaluated once
    noise_seed = [*np.atleast_1d(np.asarray(seed, np.int64)).tolist(), 7]
    filled = delete_patches(image, distinct.reshape(-1, rows, cols), fill, seed=noise_seed)
    changes = action_change(evaluate(filled), reference)[np.asarray(inverse).ravel()]
    change_all, curves, lerfs = _split_changes(changes, len(orders), len(controls), len(ks))

    valid = change_all >= MIN_CHANGE
    area = lambda c: float(auc(fractions, c)) if valid else np.nan  # noqa: E731
    control_del = np.mean([area(d) for d, _ in curves[len(orders):]])
    control_ins = np.mean([area(i) for _, i in curves[len(orders):]])
    position = {k: int(np.searchsorted(ks, k)) for k in topk}  # every top-k count is on the curve
    random_k = {k: float(np.mean([d[position[k]] for d, _ in curves[len(orders):]])) for k in topk}

    out = []
    for (name, order), (d, i), lerf in zip(orders.items(), curves, lerfs):
        row = {
            "method": name,
            "fill": fill,
            "patches": n,
            "change_all": change_all,
            "deletion_auc": area(d),
            "insertion_auc": area(i),
            "lerf_auc": area(lerf),
            "random_deletion_auc": float(control_del),
            "random_insertion_auc": float(control_ins),
            "random_lerf_auc": float(control_del),  # a reversed random order is a random order
            "fractions": fractions.tolist(),
            "deletion_curve": [float(x) for x in d],
            "insertion_curve": [float(x) for x in i],
            "lerf_curve": [float(x) for x in lerf],
        }
        for k in topk:
            row[f"top_k/{k}"] = float(d[position[k]])
            row[f"random_k/{k}"] = random_k[k]
            row[f"bottom_k/{k}"] = float(lerf[position[k]])
        out.append(row)
    return out


def _deleted_sets(orders: list[np.ndarray], controls: list[np.ndarray], ks: np.ndarray, n: int) -> np.ndarray:
    """(sets, n) bool, the deleted patches of one batch: full deletion; per ranking (methods, then random controls)
    MoRF deletion and insertion at every k; LeRF per method (its first top-k points are the bottom-k)."""
    blocks: list[np.ndarray] = [np.ones((1, n), bool)]
    for order in [*orders, *controls]:
        chosen = first_k(order, ks)
        blocks += [chosen, ~chosen]
    for order in orders:
        blocks.append(first_k(order[::-1], ks))
    return np.concatenate(blocks)


def _split_changes(changes: np.ndarray, methods: int, controls: int, points: int
                   ) -> tuple[float, list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]:
    """The batch's action changes (in `_deleted_sets` order) -> (full deletion's change, [(deletion curve, insertion
    curve)] per method then per control, [LeRF curve] per method)."""
    change_all = float(changes[0])
    at = 1
    curves = []
    for _ in range(methods + controls):
        curves.append((changes[at:at + points], changes[at + points:at + 2 * points]))
        at += 2 * points
    lerfs = []
    for _ in range(methods):
        lerfs.append(changes[at:at + points])
        at += points
    return change_all, curves, lerfs


def _ks_with(n: int, topk: Sequence[int], max_points: int) -> np.ndarray:
    return np.unique(np.concatenate([curve_points(n, max_points), np.asarray(topk, int)]))


def relative_to_random(
    values: np.ndarray,
    controls: np.ndarray,
    groups: np.ndarray,
    resamples: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float, float, int]:
    """values, controls, groups (steps,) -> (ratio, ci_low, ci_high, n_groups).

    ratio = sum(values) / sum(controls) over the steps with both finite; the interval is the percentile
    bootstrap of that ratio resampling whole groups (episodes), or steps when there is only one group.
    Seeded: the same input gives the same interval. Fewer than 2 resampling units: NaN interval.
    """
    values = np.asarray(values, np.float64)
    controls = np.asarray(controls, np.float64)
    groups = np.asarray(groups)
    ok = np.isfinite(values) & np.isfinite(controls)
    values, controls, groups = values[ok], controls[ok], groups[ok]
    if values.size == 0 or controls.sum() == 0:
        return np.nan, np.nan, np.nan, 0
    ratio = float(values.sum() / controls.sum())
    labels, index = np.unique(groups, return_inverse=True)
    if len(labels) < 2:
        index = np.arange(values.size)
    units = index.max() + 1
    num = np.bincount(index, weights=values, minlength=units)
    den = np.bincount(index, weights=controls, minlength=units)
    if units < 2:
        return ratio, np.nan, np.nan, int(len(labels))
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(units, np.full(units, 1.0 / units), size=resamples)  # (B, units)
    with np.errstate(divide="ignore", invalid="ignore"):
        boot = (counts @ num) / (counts @ den)
    boot = np.sort(boot[np.isfinite(boot)])
    if boot.size == 0:
        return ratio, np.nan, np.nan, int(len(labels))
    lo = boot[int(np.floor((boot.size - 1) * (1 - confidence) / 2))]
    hi = boot[int(np.ceil((boot.size - 1) * (1 + confidence) / 2))]
    return ratio, float(lo), float(hi), int(len(labels))


def step_faithfulness(
    batch: Callable[[dict], np.ndarray],
    images: Mapping[str, np.ndarray],
    reference: np.ndarray,
    maps: Mapping[str, Mapping[str, np.ndarray]],
    **options,
) -> list[dict]:
    """Every camera of one step: `camera_faithfulness` rows with a "camera" key.

    batch: {obs key: (m, window, H, W, 3)} -> (m, horizon, dim) chunks (a StepFunction's `batch`); images
    {obs key: (window, H, W, 3)} the step's inputs; maps {method: {obs key: (rows, cols)}}. Only the
    current (last) frame of one camera is changed at a time.
    """
    out = []
    for key, window in images.items():
        window = np.asarray(window, np.float32)

        def evaluate(frames: np.ndarray, key=key, window=window) -> np.ndarray:
            m = len(frames)
            inputs = {k: np.repeat(np.asarray(v, np.float32)[None], m, axis=0) for k, v in images.items()}
            inputs[key][:, -1] = frames
            return batch(inputs)

        camera_maps = {method: by_camera[key] for method, by_camera in maps.items() if key in by_camera}
        if not camera_maps:
            continue
        for row in camera_faithfulness(evaluate, window[-1], reference, camera_maps, **options):
            out.append({"camera": key, **row})
    return out

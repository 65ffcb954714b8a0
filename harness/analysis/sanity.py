"""Sanity checks of attribution methods and of the deletion metric: do the maps depend on the model, and how do the
patches of a camera act on the action: one at a time or jointly?

Model-parameter randomisation (Adebayo et al. 2018, "Sanity Checks for Saliency Maps"; Quantus's "Model Parameter
Randomisation Test"): the maps of the trained policy are compared, on the same inputs (same frames, same rng), with
the maps of the policy whose weights were re-drawn, block by block. Two schedules:
  cascading    from the top down: the action head, then the transformer blocks from the last to the first, then
               everything below them (image stems, projections, position and readout embeddings); each stage keeps
               the blocks above it randomised;
  independent  each of those blocks alone.
A re-drawn array keeps its shape and is drawn from N(mean, std) of the trained array (the scale the network was
trained at, so activations neither vanish nor explode; a constant array such as a norm's scale stays constant).
Similarity per step, method and camera: Spearman's rank correlation of the patch scores (`spearman`) and SSIM
of the two maps scaled to [0, 1] (`ssim`: one window over the whole map: the grids are 4x4 to 8x8 patches, smaller
than SSIM's usual 7x7 window). Means over steps with percentile-bootstrap 95% intervals over steps.
Rule (`verdict`): a method PASSES on a camera when, with every block randomised (the cascade's last stage), the
upper end of the 95% interval of the mean Spearman correlation is below `PASS_BELOW` (0.5): its ranking has
mostly gone with the weights. The random map, drawn from the same seed whatever the weights, fails by construction:
it is the control that shows the check can fail.

Additivity of single-patch effects (`patch_effects`): the action's change vector when one patch alone is deleted
(occlusion), and when a set of patches is deleted together; additivity = |change(set)| / |sum of the set's single
changes| and the cosine between the two (1 and 1 for an action additive over patches; << 1: the set's effect is
not the sum, so patches act jointly and no single ordering captures them).

Pure numpy functions; `randomised_params` takes and returns a parameter tree (nested dicts of arrays).
"""

from __future__ import annotations

import zlib
from typing import Callable, Mapping, Sequence

import numpy as np
from scipy.stats import rankdata

from harness.analysis.bootstrap import bootstrap_mean_ci
from harness.verdicts import SanityVerdict  # a method's verdict per camera: pass, fail, n/a

PASS_BELOW = 0.5  # upper 95% bound of the mean Spearman correlation with every block randomised
SSIM_C1 = 0.01 ** 2  # SSIM's constants for a dynamic range of 1 (Wang et al. 2004: K1 = 0.01, K2 = 0.03)
SSIM_C2 = 0.03 ** 2


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation of two maps (any shape, same size; ties get average ranks). NaN when either is
    constant (no ranking to compare)."""
    x = rankdata(np.asarray(a, np.float64).ravel())
    y = rankdata(np.asarray(b, np.float64).ravel())
    if x.size != y.size:
        raise ValueError(f"maps differ in size: {np.shape(a)} and {np.shape(b)}")
    x, y = x - x.mean(), y - y.mean()
    denominator = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / denominator) if denominator > 0 else float("nan")


def unit_scale(m: np.ndarray) -> np.ndarray:
    """A map scaled to [0, 1] (min -> 0, max -> 1); a constant map -> zeros."""
    m = np.asarray(m, np.float64)
    span = m.max() - m.min()
    return (m - m.min()) / span if span > 0 else np.zeros_like(m)


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Structural similarity of two maps (each scaled to [0, 1] by `unit_scale`), one window over the whole map."""
    x, y = unit_scale(a).ravel(), unit_scale(b).ravel()
    if x.size != y.size:
        raise ValueError(f"maps differ in size: {np.shape(a)} and {np.shape(b)}")
    mx, my = x.mean(), y.mean()
    vx, vy = x.var(), y.var()
    cov = ((x - mx) * (y - my)).mean()
    return float((2 * mx * my + SSIM_C1) * (2 * cov + SSIM_C2) / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2)))


# ------------------------------------------------------------------------------------------- randomisation


def octo_blocks(params: Mapping) -> list[tuple[str, list[tuple[str, ...]]]]:
    """The blocks of an Octo parameter tree from the top down: [(name, [paths of the subtrees in it])].

    head (heads_*), block_{L-1} .. block_0 (the transformer's encoderblock_i; the final encoder norm goes with the
    top block), stem (everything else under octo_transformer: tokenizers, projections, embeddings).
    """
    top = [k for k in params if k != "octo_transformer"]
    transformer = params.get("octo_transformer", {})
    blocks_tree = transformer.get("BlockTransformer_0", {}).get("Transformer_0", {})
    layers = sorted((k for k in blocks_tree if k.startswith("encoderblock_")), key=lambda k: int(k.split("_")[1]))
    out: list[tuple[str, list[tuple[str, ...]]]] = [("head", [(k,) for k in top])]
    base = ("octo_transformer", "BlockTransformer_0", "Transformer_0")
    for i, name in reversed(list(enumerate(layers))):
        paths = [(*base, name)]
        if i == len(layers) - 1:
            paths += [(*base, k) for k in blocks_tree if not k.startswith("encoderblock_")]
        out.append((f"block_{i}", paths))
    out.append(("stem", [("octo_transformer", k) for k in transformer if k != "BlockTransformer_0"]))
    return [(name, paths) for name, paths in out if paths]


def schedules(blocks: Sequence[tuple[str, list]]) -> list[tuple[str, str, list]]:
    """[(schedule, stage name, paths randomised)]: cascading stages (top down, cumulative), then each block alone.
    Cascading stage names are "up to <block>" (the last one randomises every block)."""
    out, cumulative = [], []
    for name, paths in blocks:
        cumulative = cumulative + list(paths)
        out.append(("cascading", f"up to {name}", list(cumulative)))
    out += [("independent", name, list(paths)) for name, paths in blocks]
    return out


def randomised_params(params: Mapping, paths: Sequence[tuple[str, ...]], seed) -> dict:
    """A copy of `params` (nested dicts of arrays) whose subtrees at `paths` are re-drawn: every array from
    N(mean, std) of itself, seeded by (seed, the array's path), so a block draws the same numbers whichever
    schedule it appears in. Other arrays are shared, not copied. A path not in the tree is an error."""
    out = _copy_dicts(params)
    for path in paths:
        parent = out
        for key in path[:-1]:
            if key not in parent:
                raise KeyError(f"parameter path {'/'.join(path)} is not in the model")
            parent = parent[key]
        if path[-1] not in parent:
            raise KeyError(f"parameter path {'/'.join(path)} is not in the model")
        parent[path[-1]] = _redraw(parent[path[-1]], path, seed)
    return out


def _copy_dicts(tree):
    return {k: _copy_dicts(v) for k, v in tree.items()} if isinstance(tree, Mapping) else tree


def _redraw(tree, path: tuple[str, ...], seed):
    if isinstance(tree, Mapping):
        return {k: _redraw(v, (*path, k), seed) for k, v in tree.items()}
    array = np.asarray(tree)
    rng = np.random.default_rng([*np.atleast_1d(seed).tolist(), zlib.crc32("/".join(path).encode())])
    values = array.astype(np.float64)
    return (rng.standard_normal(array.shape) * values.std() + values.mean()).astype(array.dtype)


def compare_maps(trained: Mapping[str, Mapping[str, np.ndarray]], randomised: Mapping[str, Mapping[str, np.ndarray]]
                 ) -> list[dict]:
    """{method: {camera: map}} x2 (one step) -> rows {method, camera, spearman, ssim} for every pair both have."""
    rows = []
    for method, by_camera in trained.items():
        for camera, m in by_camera.items():
            other = randomised.get(method, {}).get(camera)
            if other is not None:
                rows.append({"method": method, "camera": camera, "spearman": spearman(m, other), "ssim": ssim(m, other)})
    return rows


def summarise_randomisation(rows: Sequence[Mapping], seed: int = 0) -> list[dict]:
    """Per-step rows {schedule, stage, method, camera, spearman, ssim} -> one row per (schedule, stage, method,
    camera): steps, mean Spearman and SSIM with percentile-bootstrap 95% intervals over steps, in first-seen order."""
    groups: dict[tuple, list[Mapping]] = {}
    for row in rows:
        groups.setdefault((row["schedule"], row["stage"], row["method"], row["camera"]), []).append(row)
    out = []
    for (schedule, stage, method, camera), items in groups.items():
        values = np.array([[r["spearman"], r["ssim"]] for r in items], np.float64)  # (steps, 2)
        mean, low, high, n = bootstrap_mean_ci(values, seed=seed)
        out.append({"schedule": schedule, "stage": stage, "method": method, "camera": camera, "steps": int(n[0]),
                    "spearman": float(mean[0]), "spearman_low": float(low[0]), "spearman_high": float(high[0]),
                    "ssim": float(mean[1]), "ssim_low": float(low[1]), "ssim_high": float(high[1])})
    return out


def verdict(summary: Sequence[Mapping], last_stage: str) -> dict[tuple[str, str], SanityVerdict]:
    """{(method, camera): "pass" | "fail" | "n/a"} from the cascade's stage `last_stage` (every block randomised):
    pass when the upper 95% bound of the mean Spearman is below PASS_BELOW; n/a without an interval (< 2 steps
    with a value)."""
    out = {}
    for row in summary:
        if row["schedule"] != "cascading" or row["stage"] != last_stage:
            continue
        high = row["spearman_high"]
        out[(row["method"], row["camera"])] = (SanityVerdict.NOT_APPLICABLE if not np.isfinite(high) else
                                               SanityVerdict.PASS if high < PASS_BELOW else SanityVerdict.FAIL)
    return out


# ------------------------------------------------------------------------------------------- interactions


def patch_effects(
    evaluate: Callable[[np.ndarray], np.ndarray],
    image: np.ndarray,
    reference: np.ndarray,
    sets: Mapping[str, np.ndarray],
    *,
    fill: str = "mean",
    seed=0,
) -> dict:
    """Single-patch effects and how additive they are, one camera at one step.

    evaluate: frames (m, H, W, 3) -> (m, horizon, dim) chunks (other inputs fixed, same rng); image (H, W, 3);
    reference (horizon, dim) the chunk of the intact image; sets {name: (s, rows, cols) bool}: deleted sets to test.
    Returns {"single": (rows, cols) RMS change of each patch alone, "whole": RMS change with every patch deleted,
    name: {"change": (s,) RMS change of the set, "sum_single": (s,) RMS of the summed single changes,
    "additivity": (s,) change / sum_single, "cosine": (s,) cosine of the set's change vector and the summed one}}.
    """
    from harness.measures.faithfulness import delete_patches

    rows, cols = next(iter(sets.values())).shape[1:] if sets else (None, None)
    if rows is None:
        raise ValueError("patch_effects needs at least one set of patches")
    n = rows * cols
    single = np.eye(n, dtype=bool).reshape(n, rows, cols)
    names = list(sets)
    masks = np.concatenate([single, np.ones((1, rows, cols), bool), *[np.asarray(sets[k], bool) for k in names]])
    changes = np.asarray(evaluate(delete_patches(image, masks, fill, seed=seed)), np.float64) - np.asarray(reference)
    vectors = changes.reshape(len(masks), -1)  # (m, horizon*dim)
    rms = np.sqrt((vectors ** 2).mean(axis=1))
    out: dict = {"single": rms[:n].reshape(rows, cols), "whole": float(rms[n])}
    at = n + 1
    for name in names:
        chosen = np.asarray(sets[name], bool).reshape(-1, n)  # (s, n)
        got = vectors[at:at + len(chosen)]
        summed = chosen.astype(np.float64) @ vectors[:n]  # (s, horizon*dim)
        got_rms = np.sqrt((got ** 2).mean(axis=1))
        sum_rms = np.sqrt((summed ** 2).mean(axis=1))
        with np.errstate(invalid="ignore", divide="ignore"):
            cosine = (got * summed).sum(axis=1) / (np.linalg.norm(got, axis=1) * np.linalg.norm(summed, axis=1))
            additivity = got_rms / sum_rms
        out[name] = {"change": got_rms, "sum_single": sum_rms, "additivity": additivity, "cosine": cosine}
        at += len(chosen)
    return out


def nested_sets(order: np.ndarray, ks: Sequence[int], rows: int, cols: int) -> np.ndarray:
    """order (n,) patch indices, ks -> (len(ks), rows, cols) bool: the first k patches of the order for each k."""
    from harness.measures.faithfulness import first_k

    return first_k(np.asarray(order), ks).reshape(len(ks), rows, cols)

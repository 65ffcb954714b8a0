"""Per-episode measures of a robustness grid (harness.analysis.robustness), read from one episode's attention.npz (and
controls.npz): nuisance mass (background plus distractors), target lift and the start's nuisance mass at the model's
last layer on the primary camera, raw and content-only (blank-frame part removed), and the step-0 attention rows whose
Jensen-Shannon divergence measures the shift a perturbation causes. The module docstring of
harness.analysis.robustness defines each measure.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from harness.analysis import position as Q
from harness.measures.attention import camera_maps
from harness.bounded import open_npz

CAMERA = "image_primary"
START_STEPS = 10


def _layer_measure(z, name: str) -> np.ndarray | None:
    key = f"measures/layer/{name}"
    return np.asarray(z[key], np.float64) if key in z.files else None


def episode_measures(path, controls=None) -> dict:
    """attention.npz -> {"nuisance_mass", "distractor_mass", "background_mass", "target_lift" (episode means at the
    last layer, primary camera; nan when absent), "step0_rows" (layers, keys) normalised step-0 attention,
    "step0_lift" (layers,)}; with `controls` (the episode's controls.npz, when it has a blank control) also
    "nuisance_content", "target_lift_content", "nuisance_start_content" (content_measures)."""
    with open_npz(path) as z:
        background = _layer_measure(z, f"mask_mass/{CAMERA}/background")
        distractors = [np.asarray(z[k], np.float64) for k in z.files
                       if k.startswith(f"measures/layer/mask_mass/{CAMERA}/distractor_")]
        lift = _layer_measure(z, f"mask_lift/{CAMERA}/target")
        attention = z["readout_attention"] if "readout_attention" in z.files else None
        attn = np.asarray(attention[0], np.float64) if attention is not None else None
        content = {}
        if controls is not None and attention is not None:
            with open_npz(controls) as c:
                if "blank" in c.files and "step" in c.files:
                    arrays = {k: z[k] for k in z.files if k.startswith(("tokens/", f"mask_fraction/{CAMERA}/")) or k == "step"}
                    content = content_measures(attention, arrays, np.asarray(c["step"]), c["blank"])
    out = {"nuisance_mass": math.nan, "distractor_mass": math.nan, "background_mass": math.nan, "target_lift": math.nan,
           "nuisance_start": math.nan, "step0_rows": None, "step0_lift": None}
    with warnings.catch_warnings():  # an all-nan column (a target never in view) gives a nan mean, not a warning
        warnings.simplefilter("ignore", RuntimeWarning)
        return {**_episode_means(background, distractors, lift, attn, out), **content}


def content_measures(attention: np.ndarray, arrays: dict, control_steps: np.ndarray, blank: np.ndarray) -> dict:
    """The nuisance and target measures on the content-only map of one episode, at its control steps.

    attention (steps, layers, heads, readouts, keys) the episode's readout attention; arrays: its "step" (steps,),
    tokens/* and mask_fraction/<CAMERA>/<mask> (steps, rows, cols); control_steps (n,) and blank (n, layers, heads,
    readouts, keys) from controls.npz. {} when the controls do not match the episode (steps it never recorded,
    another shape) or the camera has no masks."""
    from harness.octo.tokens import TokenMap

    steps = np.asarray(arrays.get("step", np.arange(len(attention))))
    index = {int(s): i for i, s in enumerate(steps)}
    wanted = [int(s) for s in control_steps]
    if not wanted or any(s not in index for s in wanted) or tuple(blank.shape[1:]) != tuple(attention.shape[1:]):
        return {}
    rows = [index[s] for s in wanted]
    fractions = {k.rsplit("/", 1)[1]: np.asarray(v, np.float64)[rows] for k, v in arrays.items()
                 if k.startswith(f"mask_fraction/{CAMERA}/") and len(v) == len(steps)}
    if "background" not in fractions:
        return {}
    tokens = TokenMap.from_arrays(arrays)
    real = camera_maps(np.asarray(attention[rows][:, -1], np.float64).mean(axis=(1, 2)), tokens, CAMERA)
    empty = camera_maps(np.asarray(blank[:, -1], np.float64).mean(axis=(1, 2)), tokens, CAMERA)  # (n, rows, cols)
    return content_means(real, empty, fractions, np.asarray(wanted))


def content_means(real: np.ndarray, blank: np.ndarray, fractions: dict, steps: np.ndarray) -> dict:
    """Camera maps real, blank (n, rows, cols) at n control steps (`steps` (n,)), mask coverage {"background",
    "distractor_<i>", "target": (n, rows, cols)} -> {"nuisance_content", "nuisance_start_content" (steps before
    START_STEPS), "target_lift_content"}: mass on background plus distractors, and the target's mass / area, of
    position.content_only(real, blank); means over the steps (nan where nothing content-bound is left)."""
    content = Q.content_only(real, blank)
    nuisance_cover = fractions["background"] + sum((v for k, v in fractions.items() if k.startswith("distractor_")),
                                                   np.zeros_like(fractions["background"]))
    total = content.sum(axis=(-2, -1))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # no step with content left, or no target in view: nan
        nuisance = np.where(total > 0, (content * nuisance_cover).sum(axis=(-2, -1)) / np.where(total > 0, total, 1), np.nan)
        lift = Q.mask_lift(content, fractions["target"]) if "target" in fractions else np.full(len(total), np.nan)
        start = np.asarray(steps) < START_STEPS
        return {"nuisance_content": float(np.nanmean(nuisance)), "target_lift_content": float(np.nanmean(lift)),
                "nuisance_start_content": float(np.nanmean(nuisance[start])) if start.any() else math.nan}


def _episode_means(background, distractors, lift, attn, out) -> dict:
    if background is not None and background.size:
        dis = np.sum(distractors, axis=0) if distractors else np.zeros_like(background)
        out["background_mass"] = float(np.nanmean(background[:, -1]))
        out["distractor_mass"] = float(np.nanmean(dis[:, -1]))
        out["nuisance_mass"] = float(np.nanmean((background + dis)[:, -1]))
        out["nuisance_start"] = float(np.nanmean((background + dis)[:START_STEPS, -1]))
    if lift is not None and lift.size:
        out["target_lift"] = float(np.nanmean(lift[:, -1]))
        out["step0_lift"] = lift[0]
    if attn is not None:
        rows = attn.mean(axis=(1, 2))  # (layers, keys)
        out["step0_rows"] = rows / rows.sum(axis=-1, keepdims=True)
    return out


def js_divergence_bits(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Jensen-Shannon divergence in bits between distributions along the last axis: (..., k), (..., k) -> (...)."""
    p = np.asarray(p, np.float64)
    q = np.asarray(q, np.float64)
    p = p / p.sum(axis=-1, keepdims=True)
    q = q / q.sum(axis=-1, keepdims=True)
    m = 0.5 * (p + q)

    def kl(a, b):
        with np.errstate(divide="ignore", invalid="ignore"):
            terms = np.where(a > 0, a * np.log2(a / b), 0.0)
        return terms.sum(axis=-1)

    return 0.5 * kl(p, m) + 0.5 * kl(q, m)

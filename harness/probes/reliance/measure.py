"""Region reliance by intervention: how much the predicted action chunk changes when one labelled region of a
camera is replaced, beside where the attention goes (issue 45). Pure numpy functions around one evaluation
callable, as in harness.measures.faithfulness, whose fills and distance are used here, not copied. What the closed
loop computes at a sampled step is here; reading reliance.jsonl back and the nuisance reliance of an episode are
harness.probes.reliance.reader.

At a sampled step, for every camera the model reads that has label masks, and for every region of `REGION_TABLE`
the env labels there: the region's pixels of the camera's current (last) window frame are replaced by the fill
(`impute` by default: ROAD's noisy linear imputation from the pixels around the region; `mean`: the frame's mean
colour; `blur`: a Gaussian blur of the frame, sigma one patch: faithfulness.baseline_image / impute), the model is
asked again with the same inputs otherwise and the same rng key, and the change of the normalised chunk is
faithfulness.action_change (RMS over the chunk). The whole camera replaced is the reference. The unperturbed
inputs and every replaced variant go into ONE call of the batch function (the batch axis), so a step costs
1 + sum over cameras (regions with pixels + 1) forward passes in one call; a region with no pixels at this step
is not evaluated (its change is 0).

Regions: the env's mask names, under which the attention measures store mask_mass/<obs>/<name>, turned into a
partition of each camera by one table (`REGION_TABLE`, first row wins a pixel):
  target        the task's object (robosuite "target"; LIBERO's objects of interest)
  gripper, arm  the robot's hand and fingers, the rest of the robot (robosuite)
  robot         the whole robot, only where the env has no gripper/arm split (LIBERO)
  goal          the task's goal region, where it has one
  task_objects  the task's other objects: robosuite labels them in no mask (envs.segmentation TASK_OBJECT), so they
                are the pixels no other region holds (reported only when it has pixels)
  distractors   every distractor object (robosuite "distractor_<i>" together; LIBERO "distractors")
  background    robosuite "background"; LIBERO has no such mask: there it is the pixels no other region holds

The record (`region_reliance` returns a list of rows; reliance.jsonl holds one JSON line per row, with
run, task, episode and seed added by the writer as for faithfulness.jsonl): one row per step x camera x region,
  step                int, the control step
  camera              str, the observation key (image_primary, image_wrist)
  region              str, a REGION_TABLE name (or task_objects / background as derived above)
  fill                str, impute | mean | blur
  change              float >= 0, RMS change of the normalised chunk with the region replaced (0 when area is 0)
  area_fraction       float in [0, 1], the region's share of the camera's pixels at the model's resolution
  reliance_per_pixel  float or null: change / area_fraction; null when the area is 0
  reliance_share      float or null: change / (sum of change over this camera's regions at this step); null when that
                      sum is below faithfulness.MIN_CHANGE (the camera is not used at this step)
  camera_change       float >= 0, the reference: the change with the whole camera replaced (the same on every row of
                      the camera at the step)

Masks are the env's, in its image convention (the one the model reads) at the env's camera resolution; they are
resized to the model's frame by nearest neighbour at pixel centres (`resize_mask`). Only the current frame of the
window is replaced, as faithfulness does: the masks are the current frame's.
"""

from __future__ import annotations

import fnmatch
import time
from typing import Callable, Mapping

import numpy as np

from harness.measures.faithfulness import FILLS, MIN_CHANGE, action_change, baseline_image, impute, impute_factor

DEFAULT_FILL = "impute"
PATCH = 16  # pixels per patch side when no patch grid is given (Octo's image stems)
PAD = 4  # the one call's batch is padded to a multiple of this: few compiled shapes as regions come and go
NOISE_STREAM = 2  # the impute noise of a step is drawn from (seed, step, NOISE_STREAM) (faithfulness uses 1)

# (region, env mask names it is read from (fnmatch patterns), masks whose presence drops the row); order = precedence
REGION_TABLE: tuple[tuple[str, tuple[str, ...], tuple[str, ...]], ...] = (
    ("target", ("target",), ()),
    ("gripper", ("gripper",), ()),
    ("arm", ("arm",), ()),
    ("robot", ("robot",), ("gripper", "arm")),
    ("goal", ("goal",), ()),
    ("distractors", ("distractors", "distractor_*"), ()),
    ("background", ("background",), ()),
)
TASK_OBJECTS = "task_objects"  # the pixels no row holds, when the env gives a background mask
WHOLE = "whole_camera"  # not a row: the reference is each row's camera_change


def resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """mask (h, w) bool -> (height, width) bool: nearest neighbour at pixel centres (unchanged at the same size)."""
    mask = np.asarray(mask, bool)
    height, width = size
    h, w = mask.shape
    if (h, w) == (height, width):
        return mask
    ys = ((2 * np.arange(height) + 1) * h) // (2 * height)
    xs = ((2 * np.arange(width) + 1) * w) // (2 * width)
    return mask[ys[:, None], xs[None, :]]


def region_masks(named: Mapping[str, np.ndarray | None], size: tuple[int, int] | None = None) -> dict[str, np.ndarray]:
    """The env's masks of one camera {name: (h, w) bool} -> {region: (H, W) bool}, disjoint, in REGION_TABLE order.

    size (H, W): the model's frame (masks resized, `resize_mask`); None keeps theirs. A region is there when the env
    gives one of its masks (even empty at this step); the pixels no region holds are TASK_OBJECTS when the env gives
    "background", else "background"; that remainder is there only when it has pixels. Unknown names (LIBERO's
    "object.<name>", which overlap target and distractors) are not regions."""
    named = {k: v for k, v in named.items() if v is not None}
    if not named:
        return {}
    shape = tuple(size) if size is not None else np.shape(next(iter(named.values())))
    masks = {k: resize_mask(v, shape) for k, v in named.items()}
    claimed = np.zeros(shape, bool)
    out: dict[str, np.ndarray] = {}
    for region, sources, unless in REGION_TABLE:
        if any(u in masks for u in unless):
            continue
        found = [m for k, m in masks.items() if any(fnmatch.fnmatchcase(k, s) for s in sources)]
        if not found:
            continue
        mask = np.logical_or.reduce(found) & ~claimed
        claimed |= mask
        out[region] = mask
    if not claimed.all():
        out[TASK_OBJECTS if "background" in out else "background"] = ~claimed
    return out


def fill_region(image: np.ndarray, mask: np.ndarray, fill: str, grid: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """image (H, W, 3), mask (H, W) bool -> (H, W, 3) float32 with the mask's pixels replaced by `fill`.

    mean / blur: faithfulness.baseline_image (blur sigma: one patch of `grid` (rows, cols)) inside the mask; impute:
    faithfulness.impute solved on blocks of faithfulness.impute_factor for the grid, noise drawn from `rng`."""
    image = np.asarray(image, np.float32)
    mask = np.asarray(mask, bool)
    if fill == "impute":
        return impute(image, mask, rng=rng, factor=impute_factor(*image.shape[:2], *grid))
    return np.where(mask[..., None], baseline_image(image, fill, *grid), image).astype(np.float32)


def region_reliance(
    evaluate: Callable[[dict], np.ndarray],
    images: Mapping[str, np.ndarray],
    masks: Mapping[str, Mapping[str, np.ndarray]],
    *,
    fill: str = DEFAULT_FILL,
    grids: Mapping[str, tuple[int, int]] | None = None,
    seed: int = 0,
    step: int = 0,
    per_call: int | None = None,
) -> list[dict]:
    """One step's rows (see the module docstring), cameras in `images` order, regions in REGION_TABLE order.

    evaluate: {obs key: (m, window, H, W, 3) float32} -> (m, horizon, dim) normalised chunks, every input but the
    images held at the step's (same rng); images {obs key: (window, H, W, 3)} the step's inputs; masks {obs key:
    {env mask name: (h, w) bool}} of the current frame (cameras without masks give no rows); grids {obs key: (rows,
    cols)} the patch grid (blur sigma, imputation blocks; default 16-pixel patches); the impute noise is drawn from
    (seed, step, NOISE_STREAM) in row order. per_call None: the unperturbed inputs and every variant in one call,
    padded to a multiple of PAD; k: calls of k rows (the last padded to k).
    """
    if fill not in FILLS:
        raise ValueError(f"unknown reliance fill {fill!r}; use one of {', '.join(FILLS)}")
    images = {k: np.asarray(v, np.float32) for k, v in images.items()}
    rng = np.random.default_rng([int(seed), int(step), NOISE_STREAM])
    plan: list[tuple[str, dict[str, np.ndarray], dict[str, int]]] = []  # (camera, regions, region -> variant)
    variants: list[tuple[str, np.ndarray]] = []  # (camera, current frame replaced)
    for key, window in images.items():
        if not (masks or {}).get(key):
            continue
        frame = window[-1]
        height, width = frame.shape[:2]
        grid = tuple((grids or {}).get(key) or (max(1, height // PATCH), max(1, width // PATCH)))
        regions = region_masks(masks[key], (height, width))
        if not regions:
            continue
        index = {}
        for name, mask in regions.items():
            if mask.any():
                index[name] = len(variants)
                variants.append((key, fill_region(frame, mask, fill, grid, rng)))
        index[WHOLE] = len(variants)
        variants.append((key, fill_region(frame, np.ones((height, width), bool), fill, grid, rng)))
        plan.append((key, regions, index))
    if not plan:
        return []
    chunks = _evaluate_variants(evaluate, images, variants, per_call)
    changes = action_change(chunks[1:], chunks[0])  # (variants,)
    rows = []
    for key, regions, index in plan:
        change = {name: float(changes[index[name]]) if name in index else 0.0 for name in regions}
        total = sum(change.values())
        for name, mask in regions.items():
            area = float(mask.mean())
            rows.append({
                "step": int(step),
                "camera": key,
                "region": name,
                "fill": fill,
                "change": change[name],
                "area_fraction": area,
                "reliance_per_pixel": change[name] / area if area > 0 else None,
                "reliance_share": change[name] / total if total >= MIN_CHANGE else None,
                "camera_change": float(changes[index[WHOLE]]),
            })
    return rows


def _evaluate_variants(evaluate, images: dict, variants: list, per_call: int | None) -> np.ndarray:
    """(1 + len(variants), horizon, dim): the unperturbed inputs first, then each variant (one camera's current frame
    replaced), in calls of a fixed size (padded with the unperturbed inputs; padding discarded)."""
    m = 1 + len(variants)
    size = -(-m // PAD) * PAD if per_call is None else int(per_call)
    out = []
    for start in range(0, m, size):
        rows = range(start, min(m, start + size))
        inputs = {k: np.repeat(v[None], size, axis=0) for k, v in images.items()}
        for slot, row in enumerate(rows):
            if row > 0:
                key, frame = variants[row - 1]
                inputs[key][slot, -1] = frame
        out.append(np.asarray(evaluate(inputs), np.float64)[:len(rows)])
    return np.concatenate(out)


# ------------------------------------------------------------------------------------------- in a run


class RelianceProbe:
    """What a run with a reliance interval computes at an inference step, for one model.

    `due(step)`: every `every`-th control step (step % every == 0; 0 = never). `__call__(observations, task, rng,
    seed, step, masks)` (batch-1 inputs as `sample_actions` takes them, the step's rng key, the env's masks of the
    current frame {obs key: {name: (h, w) bool}} in the env's convention) -> {"rows": region_reliance rows,
    "seconds": wall time}. `functions`: an attribution.OctoFunctions of the same model to share (one compilation).
    """

    def __init__(self, model, every: int, fill: str = DEFAULT_FILL, functions=None):
        from harness.measures.attribution import OctoFunctions

        if fill not in FILLS:
            raise ValueError(f"unknown reliance fill {fill!r}; use one of {', '.join(FILLS)}")
        self.functions = functions if functions is not None else OctoFunctions(model)
        self.every = int(every)
        self.fill = fill

    def due(self, step: int) -> bool:
        return self.every > 0 and step % self.every == 0

    def __call__(self, observations: Mapping, task: Mapping, rng, seed: int, step: int, masks: Mapping | None,
                 per_call: int | None = None) -> dict:
        if masks is None:
            raise ValueError("region reliance needs the env's masks at its steps; run without --no-masks")
        start = time.perf_counter()
        fn = self.functions.at(observations, task, rng)
        grids = {key: (rows, cols) for _, key, rows, cols in fn.tokens.image_groups}
        evaluate = lambda inputs: fn.batch(inputs, chunk=len(next(iter(inputs.values()))))  # noqa: E731  (one call)
        rows = region_reliance(evaluate, fn.images, masks, fill=self.fill, grids=grids, seed=seed, step=step,
                               per_call=per_call)
        return {"rows": rows, "seconds": time.perf_counter() - start}

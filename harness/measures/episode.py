"""One episode's attention measures per step: pure numpy functions, no files, no drawing.

`episode_measures`: one episode's readout attention (steps, layers, heads, readouts, keys) + token map + mask patch
coverage -> per-step measures per layer (head mean) and per head. Across steps and episodes they are summarised by
harness.analysis.aggregate.

Metric names (the same at layer and head level):
  share/<category>        fraction of the readout rows' mass per token group (attention.modality_categories:
                          primary, wrist, language, readout, and any other group present); they sum to 1
  timestep_share/<part>   fraction on the task prefix / earlier timesteps / the current timestep; sum to 1
  entropy                 entropy of each attention row (nats), mean over readouts (and heads)
  mask_mass/<obs>/<name>  fraction of the camera's current-timestep attention inside the mask (e.g. target)
  mask_lift/<obs>/<name>  mask_mass / mask area: 1 = chance (uniform attention), 1/area = all inside the mask

Layer-level values use the definitions of attention.step_metrics (the numbers in metrics.jsonl): shares and
mask mass of the head-mean row, entropy averaged over heads and readouts.

The writers store each episode's measures in attention.npz (`measure_arrays`, "measures/..."), so a report reads a
few MB per episode instead of its full attention (`measures_from_arrays`); runs made before that are measured from
readout_attention.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Mapping

import numpy as np

from harness.measures.attention import _timestep_parts, camera_keys, modality_categories  # one definition of the parts
from harness.octo.tokens import TokenMap


def metric_selectors(tokens: TokenMap) -> dict[str, np.ndarray]:
    """metric name -> (keys,) bool selector, for the share metrics: "share/<category>" and "timestep_share/<part>"."""
    selectors = {f"share/{name}": sel for name, sel in modality_categories(tokens).items()}
    selectors.update({f"timestep_share/{name}": sel for name, sel in _timestep_parts(tokens).items()})
    return selectors


@lru_cache(maxsize=1)
def _float16_xlogx() -> np.ndarray:
    """(65536,) float64: x * log(x) for every float16 bit pattern (0 for x <= 0, inf and nan)."""
    x = np.arange(65536, dtype=np.uint16).view(np.float16).astype(np.float64)
    good = np.isfinite(x) & (x > 0)
    out = np.zeros_like(x)
    out[good] = x[good] * np.log(x[good])
    out.setflags(write=False)
    return out


def _row_xlogx(x: np.ndarray) -> np.ndarray:
    """x (..., keys) -> (...) sum of x log x over keys (float16 through a lookup table: no log per element)."""
    if x.dtype == np.float16:
        return _float16_xlogx()[x.view(np.uint16)].sum(axis=-1)
    x = x.astype(np.float64)
    logx = np.log(x, out=np.zeros_like(x), where=x > 0)
    return (x * logx).sum(axis=-1)


@dataclass(frozen=True, eq=False)
class EpisodeMeasures:
    layer: dict[str, np.ndarray]  # metric -> (steps, layers): head-mean level, as attention.step_metrics
    head: dict[str, np.ndarray]  # metric -> (steps, layers, heads)

    @property
    def steps(self) -> int:
        return int(next(iter(self.layer.values())).shape[0]) if self.layer else 0


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    return np.divide(num, den, out=np.full(np.broadcast_shapes(num.shape, den.shape), np.nan), where=den > 0)


def episode_measures(
    readout_attention: np.ndarray,
    tokens: TokenMap,
    mask_fractions: dict[str, np.ndarray] | None = None,
    mask_areas: dict[str, np.ndarray] | None = None,
    stored_mask_mass: dict[str, np.ndarray] | None = None,
    chunk: int = 32,
) -> EpisodeMeasures:
    """Per-step measures of one episode.

    readout_attention: (steps, layers, heads, readouts, keys), float16 as stored or any float.
    mask_fractions: "<obs>/<name>" -> (steps, rows, cols) patch coverage of the mask on that camera's grid
      (attention.mask_fractions per step; a step whose coverage is nan has no mask: its mass is nan).
    mask_areas: "<obs>/<name>" -> (steps,) fraction of the camera's pixels inside the mask (chance level).
    stored_mask_mass: "<obs>/<name>" -> (steps, layers) head-mean mask mass as stored by the writers; used,
      at layer level only, for masks without coverage arrays (runs made before coverage was stored).
    Returns metrics -> (steps, layers) and (steps, layers, heads); see the module docstring for names.
    """
    attn = np.asarray(readout_attention)
    if attn.ndim != 5 or attn.shape[-1] != tokens.num_keys:
        raise ValueError(f"readout attention must be (steps, layers, heads, readouts, keys={tokens.num_keys}); got {attn.shape}")
    steps, layers, heads, readouts, keys = attn.shape
    mask_fractions = dict(mask_fractions or {})
    mask_areas = dict(mask_areas or {})
    cameras = {obs for _, obs, _, _ in tokens.image_groups}
    masks = [name for name in mask_fractions if name.split("/")[0] in cameras]

    selectors = metric_selectors(tokens)
    names = list(selectors)
    cam_names = sorted({name.split("/")[0] for name in masks})
    static, cam_keys = _key_columns(tokens, selectors, cam_names)
    weights, valid = _mask_weights(mask_fractions, masks, cam_keys, steps, keys)
    sums, inside, xlogx = _row_sums(attn, static, weights, chunk)

    shape = (steps, layers, heads, readouts)
    sums = sums.reshape(*shape, -1)
    inside = inside.reshape(*shape, -1)
    total = sums[..., 0]  # (steps, layers, heads, readouts)
    with np.errstate(divide="ignore", invalid="ignore"):
        row_entropy = np.where(total > 0, np.log(np.where(total > 0, total, 1.0)) - xlogx.reshape(shape) / total, 0.0)

    layer: dict[str, np.ndarray] = {}
    head: dict[str, np.ndarray] = {}
    total_h = total.sum(axis=3)  # (steps, layers, heads)
    total_l = total_h.sum(axis=2)  # (steps, layers)
    for i, name in enumerate(names):
        mass_h = sums[..., 1 + i].sum(axis=3)
        head[name] = _ratio(mass_h, total_h)
        layer[name] = _ratio(mass_h.sum(axis=2), total_l)
    head["entropy"] = row_entropy.mean(axis=3)
    layer["entropy"] = row_entropy.mean(axis=(2, 3))
    for j, name in enumerate(masks):
        cam_h = sums[..., 1 + len(names) + cam_names.index(name.split("/")[0])].sum(axis=3)  # (steps, layers, heads)
        _mask_measures(name, inside[..., j].sum(axis=3), cam_h, valid[:, j], mask_areas, layer, head)
    for name, stored in (stored_mask_mass or {}).items():  # older runs: head-mean mask mass only
        if name in masks or name.split("/")[0] not in cameras:
            continue
        mass_l = np.asarray(stored, np.float64).reshape(steps, layers)
        layer[f"mask_mass/{name}"] = mass_l
        if name in mask_areas:
            layer[f"mask_lift/{name}"] = _ratio(mass_l, np.asarray(mask_areas[name], np.float64).reshape(steps)[:, None])
    return EpisodeMeasures(layer=layer, head=head)


def _key_columns(tokens: TokenMap, selectors: dict[str, np.ndarray], cam_names: list[str]
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(keys, 1 + selectors + cameras) float32 columns: all ones | each selector's keys | each masked camera's keys,
    and {camera: (rows*cols,) key of each patch, row-major}."""
    keys = tokens.num_keys
    static = np.zeros((keys, 1 + len(selectors) + len(cam_names)), np.float32)  # total | selectors | camera keys
    static[:, 0] = 1.0
    for i, name in enumerate(selectors):
        static[selectors[name], 1 + i] = 1.0
    cam_keys = {obs: camera_keys(tokens, obs) for obs in cam_names}  # (rows*cols,) key of each patch, row-major
    for i, obs in enumerate(cam_names):
        static[cam_keys[obs], 1 + len(selectors) + i] = 1.0
    return static, cam_keys


def _mask_weights(mask_fractions: dict[str, np.ndarray], masks: list[str], cam_keys: dict[str, np.ndarray], steps: int,
                  keys: int) -> tuple[np.ndarray, np.ndarray]:
    """((steps, keys, masks) float32 coverage of each mask at its camera's keys, 0 where unknown; (steps, masks) bool:
    the step has the mask)."""
    weights = np.zeros((steps, keys, len(masks)), np.float32)  # per step: coverage at the camera's current keys
    valid = np.ones((steps, len(masks)), bool)
    for j, name in enumerate(masks):
        obs = name.split("/")[0]
        frac = np.asarray(mask_fractions[name], np.float32).reshape(steps, -1)  # (steps, rows*cols)
        if frac.shape[1] != cam_keys[obs].size:
            raise ValueError(f"mask coverage {name} has {frac.shape[1]} patches but the token map has {cam_keys[obs].size}")
        valid[:, j] = np.isfinite(frac).all(axis=1)
        weights[:, cam_keys[obs], j] = np.where(np.isfinite(frac), frac, 0.0)
    return weights, valid


def _row_sums(attn: np.ndarray, static: np.ndarray, weights: np.ndarray, chunk: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per step and attention row (layers*heads*readouts): the sums over each column of `static` (steps, rows,
    columns), the masses inside each mask (steps, rows, masks) and sum x log x (steps, rows), float64, a chunk of
    steps at a time."""
    steps, layers, heads, readouts, keys = attn.shape
    rows = layers * heads * readouts
    masks = weights.shape[2]
    sums = np.empty((steps, rows, static.shape[1]), np.float64)
    inside = np.empty((steps, rows, masks), np.float64)
    xlogx = np.empty((steps, rows), np.float64)
    for s0 in range(0, steps, chunk):  # chunks keep the float32 copy small (cache friendly, bounded memory)
        block = attn[s0:s0 + chunk].reshape(-1, rows, keys)
        x = block.astype(np.float32)
        sums[s0:s0 + chunk] = x @ static
        if masks:
            inside[s0:s0 + chunk] = np.matmul(x, weights[s0:s0 + chunk])
        xlogx[s0:s0 + chunk] = _row_xlogx(block)
    return sums, inside, xlogx


def _mask_measures(name: str, in_h: np.ndarray, cam_h: np.ndarray, valid: np.ndarray, mask_areas: dict,
                   layer: dict, head: dict) -> None:
    """Into `layer` and `head`: mask mass (the camera's attention inside mask `name`) and, given its area, mask lift
    (mass over area, chance = 1); nan at steps without the mask. in_h, cam_h: (steps, layers, heads) masses."""
    mass_h = _ratio(in_h, cam_h)
    mass_l = _ratio(in_h.sum(axis=2), cam_h.sum(axis=2))
    mass_h[~valid] = np.nan
    mass_l[~valid] = np.nan
    head[f"mask_mass/{name}"] = mass_h
    layer[f"mask_mass/{name}"] = mass_l
    if name in mask_areas:
        area = np.asarray(mask_areas[name], np.float64).reshape(len(valid))
        head[f"mask_lift/{name}"] = _ratio(mass_h, area[:, None, None])
        layer[f"mask_lift/{name}"] = _ratio(mass_l, area[:, None])


MEASURES = "measures/"  # attention.npz prefix of stored per-step measures: measures/layer/<metric>, measures/head/<metric>


def measure_arrays(arrays: Mapping[str, np.ndarray], tokens: TokenMap) -> dict[str, np.ndarray]:
    """The contents of an attention.npz (readout_attention, mask_fraction/*, metrics/mask_area/*) -> the episode's
    measures as arrays to store next to them: "measures/layer/<metric>" (steps, layers) and
    "measures/head/<metric>" (steps, layers, heads), float32. {} without attention steps."""
    attn = arrays.get("readout_attention")
    if attn is None or np.shape(attn)[0] == 0:
        return {}

    def prefixed(prefix: str) -> dict[str, np.ndarray]:
        return {k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}

    m = episode_measures(attn, tokens, prefixed("mask_fraction/"), prefixed("metrics/mask_area/"), prefixed("metrics/mask_mass/"))
    out = {f"{MEASURES}layer/{k}": v.astype(np.float32) for k, v in m.layer.items()}
    out.update({f"{MEASURES}head/{k}": v.astype(np.float32) for k, v in m.head.items()})
    return out


def measures_from_arrays(arrays: Mapping[str, np.ndarray]) -> EpisodeMeasures | None:
    """Stored measures/* arrays -> EpisodeMeasures (None when there are none)."""
    layer = {k[len(MEASURES) + 6:]: np.asarray(v) for k, v in arrays.items() if k.startswith(MEASURES + "layer/")}
    head = {k[len(MEASURES) + 5:]: np.asarray(v) for k, v in arrays.items() if k.startswith(MEASURES + "head/")}
    return EpisodeMeasures(layer=layer, head=head) if layer else None

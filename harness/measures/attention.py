"""Attention analysis: pure numpy functions that turn rows of attention over keys into numbers and maps.

Every function takes plain arrays (plus a `TokenMap` saying what each key is) and returns arrays;
nothing here reads files, draws, or keeps state. Shapes are named in each docstring:
`keys` is the length of the transformer sequence, `readouts` the readout tokens of the last
timestep, `(rows, cols)` a camera's patch grid.

- `camera_maps`: a row of keys -> the 2-D patch map of one camera at one timestep.
- `fuse_heads`: mean / max / min over the head axis.
- `attention_rollout`, `rollout_readout_rows`: attention rollout across layers (full matrices).
- `modality_shares`, `timestep_shares`: how a row's mass splits over token groups / timesteps.
- `mask_mass`, `mask_patch_fraction`, `mask_area_fraction`: attention mass inside an
  image-resolution mask, the per-patch coverage it uses, and chance level; `mask_fractions`: the
  coverage of every camera's masks (what the writers store so mask mass can be recomputed per head).
- `entropy`: entropy of rows in nats.
- `upsample_map`: a patch map -> a patch-constant image-resolution map (used by overlays).
- `step_metrics`: the per-step summary the writers store.
"""

from __future__ import annotations

import functools

import numpy as np

from harness.octo.tokens import TokenMap

HEAD_FUSIONS = ("mean", "max", "min")

# The definition of the derived measures an episode stores beside the policy's own outputs (attention.npz's
# mask_fraction/*, metrics/*, measures/* and the task phases): the mask labels of envs/segmentation.py, the phase
# rules of envs/phases.py and the maths here. Bump it
# whenever either changes what those arrays hold; the run folder records it (manifest "measures_version") and
# `compare` then names a difference confined to them as a change of definition, not of the policy.
MEASURES_VERSION = 1  # runs written before it was recorded have none ("unrecorded")
DERIVED_PREFIXES = ("mask_fraction/", "metrics/", "measures/", "phase")  # attention.npz keys MEASURES_VERSION covers


def _timestep(tokens: TokenMap, timestep: int) -> int:
    """Absolute window index for a possibly negative `timestep` (-1 = last)."""
    window = tokens.window
    t = timestep + window if timestep < 0 else timestep
    if not 0 <= t < window:
        raise ValueError(f"timestep {timestep} is outside the window of {window}; use 0..{window - 1} or -1")
    return t


def camera_keys(tokens: TokenMap, observation_key: str, timestep: int = -1) -> np.ndarray:
    """(rows * cols,) key positions of a camera's image tokens at `timestep`, in row-major patch order."""
    group = tokens.camera_group(observation_key)
    rows, cols = tokens.grid(group)
    idx = tokens.indices(group, _timestep(tokens, timestep))
    if idx.size != rows * cols:
        raise ValueError(f"token map has {idx.size} keys for {group!r} but its grid is {rows}x{cols}")
    order = np.argsort(tokens.row[idx] * cols + tokens.col[idx], kind="stable")
    return idx[order]


def camera_maps(rows: np.ndarray, tokens: TokenMap, observation_key: str, timestep: int = -1) -> np.ndarray:
    """rows (..., keys) -> (..., grid_rows, grid_cols): the camera's patch keys at `timestep` as a 2-D map.

    Values are the raw attention weights (not renormalised over the camera).
    """
    rows = np.asarray(rows)
    if rows.shape[-1] != tokens.num_keys:
        raise ValueError(f"attention rows have {rows.shape[-1]} keys but the token map has {tokens.num_keys}")
    grid = tokens.grid(tokens.camera_group(observation_key))
    return rows[..., camera_keys(tokens, observation_key, timestep)].reshape(*rows.shape[:-1], *grid)


def fuse_heads(x: np.ndarray, how: str = "mean", axis: int = -3) -> np.ndarray:
    """Reduce the head axis with mean, max or min.

    The default axis -3 is the head axis of both (layers, heads, readouts, keys) and (heads, q, k).
    """
    if how == "mean":
        return np.mean(x, axis=axis)
    if how == "max":
        return np.max(x, axis=axis)
    if how == "min":
        return np.min(x, axis=axis)
    raise ValueError(f"unknown head fusion {how!r}; use one of {HEAD_FUSIONS}")


def _normalise_rows(a: np.ndarray) -> np.ndarray:
    """Divide each row (last axis) by its sum; all-zero rows stay zero."""
    total = a.sum(axis=-1, keepdims=True)
    return np.divide(a, total, out=np.zeros_like(a), where=total > 0)


def _rollout_layers(full: np.ndarray, residual: bool, head_fusion: str) -> np.ndarray:
    """full (..., layers, heads, q, k) -> (..., layers, q, k) float64: fused heads, residual identity, rows renormalised."""
    full = np.asarray(full)
    if full.ndim < 4 or full.shape[-1] != full.shape[-2]:
        raise ValueError(f"attention rollout needs full square matrices (layers, heads, q, k); got shape {full.shape}")
    layers = fuse_heads(full, head_fusion, axis=-3).astype(np.float64)  # fuse first: heads x smaller in float64
    if residual:
        layers = 0.5 * layers + 0.5 * np.eye(layers.shape[-1])
    return _normalise_rows(layers)


def attention_rollout(full: np.ndarray, residual: bool = True, head_fusion: str = "mean") -> np.ndarray:
    """full (..., layers, heads, q, k) with q == k -> rollout (..., q, k).

    Per layer the heads are fused, the residual path is modelled as A = 0.5 A + 0.5 I (if
    `residual`), rows are renormalised, and layers are composed in order:
    rollout = A_L @ ... @ A_2 @ A_1, so row i says how much token i at the output depends on each input token.
    """
    layers = _rollout_layers(full, residual, head_fusion)
    result = layers[..., 0, :, :]
    for i in range(1, layers.shape[-3]):
        result = layers[..., i, :, :] @ result
    return result


def rollout_readout_rows(
    full: np.ndarray, tokens: TokenMap, residual: bool = True, head_fusion: str = "mean"
) -> np.ndarray:
    """full (..., layers, heads, keys, keys) -> (..., readouts, keys): the rollout rows of the last timestep's readouts.

    Equal to attention_rollout(full)[..., readout_index, :], computed as row vectors times matrices
    from the last layer down (readouts x keys x keys per layer instead of keys^3).
    """
    layers = _rollout_layers(full, residual, head_fusion)
    rows = layers[..., -1, tokens.readout_index, :]  # (..., readouts, keys)
    for i in range(layers.shape[-3] - 2, -1, -1):
        rows = rows @ layers[..., i, :, :]
    return rows


def modality_categories(tokens: TokenMap) -> dict[str, np.ndarray]:
    """Category name -> (keys,) bool selector.

    Image groups `obs_<name>` become `<name>` (e.g. "primary", "wrist"); "lowdim" is every other
    observation group (LowdimObsTokenizer groups such as obs_proprio), present only when such keys
    exist; "language" is task_language plus obs_task_language; "readout" is every readout group at
    any timestep; anything else is "other", present only when such keys exist.
    """
    group = tokens.group.astype(str)
    cats: dict[str, np.ndarray] = {}
    image = np.zeros(group.shape, bool)
    for name, _, _, _ in tokens.image_groups:
        sel = group == name
        cats[name.removeprefix("obs_")] = sel
        image |= sel
    language = np.isin(group, ("task_language", "obs_task_language"))
    lowdim = np.char.startswith(group, "obs_") & ~np.char.startswith(group, "obs_task_") & ~image
    if lowdim.any():
        cats["lowdim"] = lowdim
    cats["language"] = language
    cats["readout"] = np.char.startswith(group, "readout_")
    other = ~(image | lowdim | cats["language"] | cats["readout"])
    if other.any():
        cats["other"] = other
    return cats


def _shares(rows: np.ndarray, selectors: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    rows = np.asarray(rows, dtype=np.float64)
    total = rows.sum(axis=-1)
    out = {}
    for name, sel in selectors.items():
        mass = rows[..., sel].sum(axis=-1)
        out[name] = np.divide(mass, total, out=np.zeros_like(total), where=total > 0)
    return out


def modality_shares(rows: np.ndarray, tokens: TokenMap, per_timestep: bool = False) -> dict[str, np.ndarray]:
    """rows (..., keys) -> {category: (...)} fraction of each row's mass per category (see modality_categories).

    With `per_timestep`, each category is split by timestep part into "<category>/prefix",
    "<category>/earlier" and "<category>/current" (only the combinations that have keys).
    Categories (and their splits) partition the keys, so the shares of a row with mass sum to 1.
    """
    cats = modality_categories(tokens)
    if per_timestep:
        parts = _timestep_parts(tokens)
        cats = {f"{c}/{p}": sel & psel for c, sel in cats.items() for p, psel in parts.items() if (sel & psel).any()}
    return _shares(rows, cats)


def _timestep_parts(tokens: TokenMap) -> dict[str, np.ndarray]:
    """{"prefix", "earlier", "current"} -> (keys,) bool: task prefix, earlier window steps, last window step."""
    last = tokens.window - 1
    return {
        "prefix": tokens.timestep < 0,
        "earlier": (tokens.timestep >= 0) & (tokens.timestep < last),
        "current": tokens.timestep == last,
    }


def timestep_shares(rows: np.ndarray, tokens: TokenMap) -> dict[str, np.ndarray]:
    """rows (..., keys) -> {"prefix", "earlier", "current"}: (...) fractions of mass on task prefix tokens,
    on earlier timesteps of the window, and on the last (current) timestep. They sum to 1."""
    return _shares(rows, _timestep_parts(tokens))


def patch_index(size: int, cells: int) -> np.ndarray:
    """(size,) patch index of each pixel along one axis: proportional coordinates floor(i * cells / size)."""
    return (np.arange(size) * cells) // size


def upsample_map(attn_map: np.ndarray, height: int, width: int) -> np.ndarray:
    """attn_map (..., rows, cols) -> (..., height, width), patch-constant.

    Pixel (y, x) takes the value of patch (floor(y*rows/height), floor(x*cols/width)); when the sizes
    divide, each patch covers exactly its (height/rows, width/cols) block.
    """
    attn_map = np.asarray(attn_map)
    rows, cols = attn_map.shape[-2:]
    ry = patch_index(height, rows)
    cx = patch_index(width, cols)
    return attn_map[..., ry[:, None], cx[None, :]]


def mask_patch_fraction(mask: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """mask (H, W) bool -> (rows, cols) fraction of each patch's pixels inside the mask.

    Patches cover pixels as in `upsample_map` (patch-constant, proportional coordinates).
    """
    mask = np.asarray(mask, dtype=bool)
    height, width = mask.shape
    if height < rows or width < cols:
        raise ValueError(f"mask {height}x{width} is smaller than the patch grid {rows}x{cols}; pass the image-resolution mask")
    patch, pixels = _patch_ids(height, width, rows, cols)
    inside = np.bincount(patch[mask.ravel()], minlength=rows * cols)  # whole counts: the same as summing 1.0 weights
    return (inside / pixels).reshape(rows, cols)


@functools.lru_cache(maxsize=32)
def _patch_ids(height: int, width: int, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """((H*W,) patch id of each pixel, (rows*cols,) pixels in each patch) for one image size and grid, read-only:
    every mask of every step of a camera shares them."""
    ry = patch_index(height, rows)
    cx = patch_index(width, cols)
    patch = (ry[:, None] * cols + cx[None, :]).ravel()
    pixels = np.bincount(patch, minlength=rows * cols)
    patch.flags.writeable = pixels.flags.writeable = False
    return patch, pixels


def mask_mass(attn_map: np.ndarray, mask: np.ndarray) -> float:
    """attn_map (rows, cols) >= 0, mask (H, W) bool -> fraction of the map's mass inside the mask.

    The map is normalised to sum 1 over the camera; each patch's mass is spread evenly over the
    pixels it covers when upsampled (patch-constant, proportional coordinates), so the result is
    sum_p map[p] * (mask pixels in p / pixels in p). Returns nan when the map has no mass.
    """
    attn_map = np.asarray(attn_map, dtype=np.float64)
    return float(_mass_inside(attn_map, mask_patch_fraction(mask, *attn_map.shape)))


def _mass_inside(maps: np.ndarray, fraction: np.ndarray) -> np.ndarray:
    """maps (..., rows, cols), fraction (rows, cols) -> (...) normalised mass inside; nan where a map has no mass."""
    total = maps.sum(axis=(-2, -1))
    inside = (maps * fraction).sum(axis=(-2, -1))
    return np.divide(inside, total, out=np.full_like(total, np.nan), where=total > 0)


def mask_fractions(tokens: TokenMap, masks: dict[str, dict[str, np.ndarray]] | None) -> dict[str, np.ndarray]:
    """masks: observation key -> {mask name: (H, W) bool} -> {"<obs>/<name>": (rows, cols) float32 patch coverage}.

    The per-patch coverage (`mask_patch_fraction`) on each camera's own patch grid: with the attention rows it
    gives the mask mass of any head, layer or readout later (sum_p map[p] * fraction[p] / sum_p map[p]).
    Cameras the model has no image group for, and missing masks, are left out.
    """
    out: dict[str, np.ndarray] = {}
    for _, obs_key, rows, cols in tokens.image_groups:
        for name, mask in ((masks or {}).get(obs_key) or {}).items():
            if mask is not None:
                out[f"{obs_key}/{name}"] = mask_patch_fraction(mask, rows, cols).astype(np.float32)
    return out


def mask_area_fraction(mask: np.ndarray) -> float:
    """mask (H, W) bool -> fraction of pixels inside: the mask mass of uniform attention (chance level)."""
    return float(np.asarray(mask, dtype=bool).mean())


def entropy(rows: np.ndarray, axis: int = -1) -> np.ndarray:
    """Entropy in nats of the distribution proportional to `rows` along `axis` (zeros contribute nothing).

    rows (..., keys) -> (...). A row with no mass has entropy 0.
    """
    p = np.asarray(rows, dtype=np.float64)
    total = p.sum(axis=axis, keepdims=True)
    p = np.divide(p, total, out=np.zeros_like(p), where=total > 0)
    logp = np.log(p, out=np.zeros_like(p), where=p > 0)
    return -(p * logp).sum(axis=axis)


def step_metrics(
    readout_attention: np.ndarray,
    tokens: TokenMap,
    masks: dict[str, dict[str, np.ndarray]] | None = None,
) -> dict[str, np.ndarray]:
    """Per-step summary of readout attention, flat dict of arrays (keys are stable for a model and env).

    readout_attention (layers, heads, readouts, keys); masks: observation key -> {mask name: (H, W) bool}.
    Returns, with rows averaged over heads and readouts per layer:
      "share/<category>"          (layers,) modality shares (see modality_categories)
      "timestep_share/<part>"     (layers,) prefix / earlier / current
      "entropy"                   (layers,) mean over heads and readouts of each row's entropy (nats)
      "mask_mass/<obs>/<name>"    (layers,) mask_mass of the head-mean camera map at the last timestep
      "mask_area/<obs>/<name>"    () chance level for that mask
    Masks for cameras the model has no image group for are ignored.
    """
    attn = np.asarray(readout_attention, dtype=np.float64)
    if attn.ndim != 4:
        raise ValueError(f"readout attention must be (layers, heads, readouts, keys); got shape {attn.shape}")
    mean_rows = attn.mean(axis=(1, 2))  # (layers, keys)
    out: dict[str, np.ndarray] = {}
    for name, value in modality_shares(mean_rows, tokens).items():
        out[f"share/{name}"] = value
    for name, value in timestep_shares(mean_rows, tokens).items():
        out[f"timestep_share/{name}"] = value
    out["entropy"] = entropy(attn).mean(axis=(1, 2))
    cameras = {key for _, key, _, _ in tokens.image_groups}
    for obs_key, named in (masks or {}).items():
        if obs_key not in cameras or not named:
            continue
        maps = camera_maps(mean_rows, tokens, obs_key)  # (layers, rows, cols)
        for name, mask in named.items():
            if mask is None:
                continue
            fraction = mask_patch_fraction(mask, *maps.shape[-2:])
            out[f"mask_mass/{obs_key}/{name}"] = _mass_inside(maps, fraction)
            out[f"mask_area/{obs_key}/{name}"] = np.array(mask_area_fraction(mask))
    return out

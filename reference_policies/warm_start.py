"""Warm start: initialise a new reference model from an earlier checkpoint's parameters.

Every parameter whose path and shape match is copied. A patch-grid position embedding whose grid changed
size (a camera now resized to more pixels, so more patches) is resampled bilinearly over the grid: the
SmallStem16 convolutions, the transformer and the heads do not depend on the image size, so after this the
new model computes on a finer grid what the old one computed on the coarse one, and training starts from
a policy that already acts. The frozen language encoder's word table may differ in its number of rows (a new
task set has another word vocabulary): the fresh, seeded table stays. Anything else that differs (a new
parameter, a changed width) is an error:
warm-starting across architectures would silently keep a random part.
"""

from __future__ import annotations

import functools
import logging
import math
from pathlib import Path

import jax
import numpy as np
from flax import traverse_util

from harness.octo.checkpoint import read_params, select_step

log = logging.getLogger(__name__)

FROZEN_ENCODER = "octo_transformer/task_tokenizers_language/"  # the frozen T5 (reference_policies.train.split_t5)


def resize_grid_embedding(embedding: np.ndarray, tokens: int) -> np.ndarray:
    """(..., n, D) position embedding over a square sqrt(n) x sqrt(n) patch grid (row-major, as the image
    tokenizer flattens it) -> (..., tokens, D) over a sqrt(tokens) grid, bilinear (align-corners=False)."""
    embedding = np.asarray(embedding, np.float32)
    *lead, n, width = embedding.shape
    side, new_side = math.isqrt(n), math.isqrt(tokens)
    if side * side != n or new_side * new_side != tokens:
        raise ValueError(f"position embeddings over {n} -> {tokens} tokens are not square patch grids")
    grid = embedding.reshape(*lead, side, side, width)
    resized = jax.image.resize(grid, (*lead, new_side, new_side, width), method="bilinear")
    return np.asarray(resized, np.float32).reshape(*lead, tokens, width)


def _plan(target: dict, source: dict, folder: Path) -> dict[tuple, str]:
    """{parameter key: "copy" | "resize" | "fresh"} for each of `target`'s (flattened; arrays or shape structs) taken
    from `source` (the checkpoint's, flattened); ValueError naming the first that cannot be."""
    plan = {}
    for key, value in target.items():
        path = "/".join(key)
        if key not in source:
            raise ValueError(f"--init-from {folder}: it has no parameter {path}; warm-start from a checkpoint of the "
                             "same architecture (or train from scratch without --init-from)")
        old = tuple(np.shape(source[key]))
        if old == tuple(value.shape):
            plan[key] = "copy"
        elif path.endswith("_pos_embedding") and old[:-2] == tuple(value.shape[:-2]) and old[-1] == value.shape[-1]:
            plan[key] = "resize"
        elif path.startswith(FROZEN_ENCODER) and old[1:] == tuple(value.shape[1:]):
            # the frozen language encoder's word table over another vocabulary (other tasks' words): its rows
            # belong to other words, so the fresh (seeded) table stays
            plan[key] = "fresh"
        else:
            raise ValueError(f"--init-from {folder}: {path} has shape {old}, the new model needs {tuple(value.shape)}; "
                             "only patch-grid position embeddings can change size")
    return plan


def _source(folder: Path) -> dict:
    return traverse_util.flatten_dict(read_params(folder, select_step(folder, None)))  # {(key, ...): array}


def warm_start(params: dict, folder: str | Path) -> tuple[dict, dict]:
    """`params` (a freshly initialised tree) with the checkpoint in `folder` (latest step) copied in.

    Returns (params, {"copied": n, "resized": [paths]}). Raises ValueError naming the first parameter
    that is missing from the checkpoint or has a shape it cannot be resampled from.
    """
    folder = Path(folder)
    source = _source(folder)
    return _copy_in(params, source, _plan(traverse_util.flatten_dict(params), source, folder), folder)


def _copy_in(params: dict, source: dict, plan: dict[tuple, str], folder: Path) -> tuple[dict, dict]:
    """warm_start's result: `params` with `source` copied in as `plan` says."""
    target = traverse_util.flatten_dict(params)
    out, resized, fresh = {}, [], []
    for key, action in plan.items():
        path, value = "/".join(key), target[key]
        old = np.asarray(source[key], np.float32)
        if action == "copy":
            out[key] = old
        elif action == "resize":
            out[key] = resize_grid_embedding(old, value.shape[-2])
            resized.append(f"{path} {old.shape} -> {value.shape}")
        else:
            out[key] = np.asarray(value, np.float32)
            fresh.append(f"{path} {old.shape} -> {value.shape}")
    log.info("warm start from %s: %d parameters copied, %d resized (%s), %d kept fresh (%s)", folder,
             len(out) - len(resized) - len(fresh), len(resized), "; ".join(resized) or "none", len(fresh),
             "; ".join(fresh) or "none")
    summary = {"copied": len(out) - len(resized) - len(fresh), "resized": resized}
    if fresh:
        summary["fresh"] = fresh
    return traverse_util.unflatten_dict(out), summary


def initialise(key, init, init_from: str | Path | None) -> tuple[dict, dict | None]:
    """(`init(key)`'s fresh parameters, or with `init_from`'s checkpoint copied in; the warm start's summary or None).

    A checkpoint that cannot warm-start the model is refused from the initialiser's shapes (`jax.eval_shape`), before
    anything is initialised or compiled. The initialiser is one compiled program: run eagerly it compiles each of its
    ~400 operations on its own (2.5x slower cold); its values differ from the eager ones by float rounding only (at
    most 3e-8 on the tiny test network), and a warm start copies every parameter anyway.
    """
    if not init_from:
        return _jitted(init)(key), None
    folder = Path(init_from)
    source = _source(folder)  # read once: checked against the shapes, then copied in
    plan = _plan(traverse_util.flatten_dict(jax.eval_shape(init, key)), source, folder)
    return _copy_in(_jitted(init)(key), source, plan, folder)


@functools.lru_cache(maxsize=8)
def _jitted(init):
    """`jax.jit(init)`, one per initialiser function: an initialiser handed in again (reference_policies.train's, one
    per network configuration) runs its compiled program again, without tracing and lowering it anew."""
    return jax.jit(init)

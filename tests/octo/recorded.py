"""Helpers for the Octo tests: the reference fixture's recorded inputs as Octo observation/task dicts."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

IMAGE_KEYS = ("image_primary", "image_wrist")


def load_expected(fixtures_dir: Path, name: str) -> dict[str, np.ndarray]:
    with np.load(fixtures_dir / f"{name}_expected.npz") as z:
        return {k: z[k] for k in z.files}


def observations(e: dict) -> dict:
    obs = {k: e[f"input/observation/{k}"] for k in IMAGE_KEYS}
    obs["timestep_pad_mask"] = e["input/observation/timestep_pad_mask"]
    obs["pad_mask_dict"] = {k: e[f"input/observation/pad_mask_dict/{k}"] for k in IMAGE_KEYS}
    return obs


def task(e: dict, prefix: str = "input/task/") -> dict:
    """The recorded task; prefix "goaltask/input/task/" gives tiny's goal-image task with padded language."""
    t = {k: e[f"{prefix}{k}"] for k in IMAGE_KEYS}
    t["pad_mask_dict"] = {k: e[f"{prefix}pad_mask_dict/{k}"] for k in IMAGE_KEYS}
    if f"{prefix}language_instruction/input_ids" in e:
        t["language_instruction"] = {k: e[f"{prefix}language_instruction/{k}"] for k in ("input_ids", "attention_mask")}
        t["pad_mask_dict"]["language_instruction"] = e[f"{prefix}pad_mask_dict/language_instruction"]
    return t


def threefry_flag(e: dict) -> str:
    """'true' or 'false': which recorded bit stream this JAX produces for PRNGKey(0)."""
    normal = np.asarray(jax.random.normal(jax.random.PRNGKey(0), (8,)))
    split = np.asarray(jax.random.key_data(jax.random.split(jax.random.PRNGKey(0))))
    for flag in ("true", "false"):
        # the key bits are integer arithmetic (equal on every machine); the normal draws go through float code that XLA
        # compiles per instruction set (XLA_FLAGS=--xla_cpu_max_isa=SSE4_2 moves them by an ulp), so they compare
        # within 1e-6: the two recorded streams differ by O(1)
        if np.array_equal(split, e[f"rng_probe/threefry_partitionable_{flag}/split_key0"]) and np.allclose(
            normal, e[f"rng_probe/threefry_partitionable_{flag}/normal_key0_8"], rtol=0, atol=1e-6
        ):
            return flag
    raise AssertionError("PRNGKey(0) matches neither recorded threefry stream")

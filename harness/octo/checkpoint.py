"""Reading Octo checkpoints: where they are, which step, and their files, with one-line errors.

Layout written by Octo's `save_pretrained` (and on the Hugging Face hub):
  config.json, example_batch.msgpack, dataset_statistics.json,
  <step>/default/checkpoint   one msgpack blob of the param dict (orbax "aggregate" file)
Other orbax layouts under `<step>/default` are restored with orbax's PyTreeCheckpointer.
`hf://owner/name` goes through huggingface_hub's snapshot download (HF cache, honours HF_HUB_OFFLINE).
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from flax import serialization, traverse_util

from harness.bounded import BoundsError, read_json
from harness.octo.errors import (
    CheckpointNotFoundError,
    ConfigError,
    CorruptCheckpointError,
    HubUnavailableError,
    ParamTreeMismatchError,
)

log = logging.getLogger(__name__)

HF_PREFIX = "hf://"


def resolve_checkpoint_dir(uri: str, cache_dir: str | Path | None = None) -> Path:
    """Local directory of a checkpoint uri (a path, or hf://owner/name downloaded into the HF cache)."""
    if uri.startswith(HF_PREFIX):
        return _download(uri[len(HF_PREFIX):].strip("/"), cache_dir)
    path = Path(uri).expanduser()
    if not path.is_dir():
        raise CheckpointNotFoundError(
            f"checkpoint directory {path} does not exist; pass an Octo checkpoint folder, hf://owner/name or random:<preset>"
        )
    return path


def _download(repo_id: str, cache_dir: str | Path | None) -> Path:
    import huggingface_hub
    from huggingface_hub import constants as hf_constants
    from huggingface_hub import utils as hf_errors

    try:
        return Path(huggingface_hub.snapshot_download(repo_id, cache_dir=cache_dir))
    except (hf_errors.LocalEntryNotFoundError, hf_errors.OfflineModeIsEnabled) as e:
        why = "HF_HUB_OFFLINE=1" if hf_constants.HF_HUB_OFFLINE else "the hub could not be reached"
        raise HubUnavailableError(
            f"hf://{repo_id} is not in the Hugging Face cache and {why}; run once online (unset HF_HUB_OFFLINE) "
            "or pass a local checkpoint path"
        ) from e
    except (hf_errors.RepositoryNotFoundError, hf_errors.RevisionNotFoundError, hf_errors.HFValidationError) as e:
        raise HubUnavailableError(f"hf://{repo_id} is not a Hugging Face model repo; check the name (hf://owner/name)") from e


def require_file(ckpt_dir: Path, name: str) -> Path:
    path = ckpt_dir / name
    if not path.is_file():
        raise CheckpointNotFoundError(f"{path} is missing; an Octo checkpoint folder needs {name} (as save_pretrained writes it)")
    return path


def available_steps(ckpt_dir: Path) -> list[int]:
    return sorted(int(p.name) for p in ckpt_dir.iterdir() if p.is_dir() and p.name.isdigit())


def select_step(ckpt_dir: Path, step: int | None) -> int:
    """The requested step, or the latest one present."""
    steps = available_steps(ckpt_dir)
    if not steps:
        raise CheckpointNotFoundError(f"{ckpt_dir} has no <step>/ parameter folder; pass a checkpoint saved by Octo's save_pretrained")
    if step is None:
        return steps[-1]
    if step not in steps:
        raise CheckpointNotFoundError(f"step {step} not in {ckpt_dir}; available steps: {steps}")
    return step


def read_params(ckpt_dir: Path, step: int) -> dict:
    """Nested dict of numpy parameter arrays for `step` (msgpack aggregate file, else orbax)."""
    default = ckpt_dir / str(step) / "default"
    blob = default / "checkpoint"
    if blob.is_file():
        try:
            tree = serialization.msgpack_restore(blob.read_bytes())
        except Exception as e:  # msgpack raises several types for truncated or foreign data
            raise CorruptCheckpointError(
                f"{blob} is corrupt or truncated ({type(e).__name__}); re-download or re-save the checkpoint"
            ) from None
        if not isinstance(tree, Mapping) or not _all_arrays(tree):
            log.info("%s is not a self-contained msgpack param dict; restoring with orbax", blob)
            return _orbax_restore(default)
        return _unwrap(tree)
    if default.is_dir():
        return _orbax_restore(default)
    raise CheckpointNotFoundError(f"{default} is missing; the step folder has no parameters (expected <step>/default/checkpoint)")


_BLOCK = re.compile(r"^encoderblock_(\d+)$")


def check_layer_count(params: Mapping, num_layers: int, config_path: Path) -> None:
    """The transformer's layer count in config.json against the encoder blocks the parameter files hold, before any
    model is built (tracing a config's 10000 layers took minutes and gigabytes before anything refused it)."""
    blocks = {int(m.group(1)) for path in traverse_util.flatten_dict(dict(params)) for part in path
              if isinstance(part, str) and (m := _BLOCK.match(part))}
    if blocks and len(blocks) != num_layers:
        raise ConfigError(f"{config_path} says num_layers {num_layers} but the checkpoint's parameter files hold "
                          f"{len(blocks)} encoder blocks; restore the checkpoint's own config.json")


def _orbax_restore(path: Path) -> dict:
    import orbax.checkpoint as ocp

    try:
        tree = ocp.PyTreeCheckpointer().restore(str(path.resolve()))
    except Exception as e:
        raise CorruptCheckpointError(f"orbax could not restore {path} ({type(e).__name__}: {e}); re-download or re-save the checkpoint") from None
    return _unwrap(tree)


def _unwrap(tree: Mapping) -> dict:
    tree = dict(tree)
    if set(tree) == {"params"}:
        tree = dict(tree["params"])
    return traverse_util.unflatten_dict({k: np.asarray(v) for k, v in traverse_util.flatten_dict(tree).items()})


def _all_arrays(tree: Mapping) -> bool:
    return all(isinstance(v, (np.ndarray, np.generic)) for v in traverse_util.flatten_dict(dict(tree)).values())


def read_example_batch(ckpt_dir: Path) -> dict:
    """example_batch.msgpack with Octo's shims for older checkpoints ("tasks" -> "task", "pad_mask")."""
    path = require_file(ckpt_dir, "example_batch.msgpack")
    try:
        batch = serialization.msgpack_restore(path.read_bytes())
    except Exception as e:
        raise CorruptCheckpointError(f"{path} is corrupt or truncated ({type(e).__name__}); re-download the checkpoint") from None
    batch = dict(batch)
    if "tasks" in batch and "task" not in batch:
        batch["task"] = batch.pop("tasks")
    obs = dict(batch.get("observation", {}))
    if "timestep_pad_mask" not in obs and "pad_mask" in obs:
        obs["timestep_pad_mask"] = obs["pad_mask"]
    batch["observation"] = obs
    return batch


def read_dataset_statistics(ckpt_dir: Path) -> dict:
    """dataset_statistics.json with list leaves as numpy arrays ({} if the file is absent)."""
    path = ckpt_dir / "dataset_statistics.json"
    if not path.is_file():
        log.warning("%s is missing; actions can only be returned normalised", path)
        return {}
    try:
        stats = read_json(path)
    except BoundsError as e:
        raise CorruptCheckpointError(f"{e}; re-download the checkpoint") from None
    except json.JSONDecodeError as e:
        raise CorruptCheckpointError(f"{path} is not valid JSON ({e}); re-download the checkpoint") from None
    return _arrays(stats)


def _arrays(node: Any) -> Any:
    if isinstance(node, Mapping):
        return {k: _arrays(v) for k, v in node.items()}
    if isinstance(node, list):
        return np.asarray(node)
    return node


def check_param_tree(expected: Mapping, found: Mapping, limit: int = 4) -> None:
    """Raise ParamTreeMismatchError listing the first mismatched paths (missing, unexpected, wrong shape).

    expected: tree of objects with `.shape` (e.g. from jax.eval_shape); found: tree of arrays.
    """
    exp = {"/".join(k): tuple(v.shape) for k, v in traverse_util.flatten_dict(dict(expected)).items()}
    got = {"/".join(k): tuple(np.shape(v)) for k, v in traverse_util.flatten_dict(dict(found)).items()}
    problems = []
    for path in sorted(set(exp) | set(got)):
        if path not in got:
            problems.append(f"{path}: expected {exp[path]}, missing in checkpoint")
        elif path not in exp:
            problems.append(f"{path}: unexpected in checkpoint {got[path]}")
        elif exp[path] != got[path]:
            problems.append(f"{path}: expected {exp[path]}, found {got[path]}")
    if problems:
        shown = "; ".join(problems[:limit]) + (f"; ... ({len(problems) - limit} more)" if len(problems) > limit else "")
        raise ParamTreeMismatchError(
            f"checkpoint parameters do not fit config.json ({len(problems)} mismatches: {shown}); "
            "use the config.json saved with these parameters"
        )

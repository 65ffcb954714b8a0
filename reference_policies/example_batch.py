"""The example batch a reference checkpoint carries (example_batch.msgpack), built as Octo's finetuning builds its own.

Octo saves the first element of its first training batch with the model, so a checkpoint's example frames are real
training frames: at the training size and orientation, as the policy was fed them. The pre-flight check
(harness.run.preflight) compares a run's first frames against them. The reference trainer does the same here:
`example_batch_from` takes a training batch as `reference_policies.train` samples it, before augmentation.
Its proprio and action chunk are normalised, as the training batch holds them (and as Octo's example batch does).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np


def example_batch_from(batch: Mapping[str, np.ndarray], language: Mapping[str, np.ndarray]) -> dict:
    """Octo's example batch from a training batch's first element.

    batch: {image key: (B, 1, H, W, 3) uint8 (training size and orientation), "proprio": (B, 1, P) normalised,
            "actions": (B, horizon, A) the normalised action chunk from that frame, "instruction": (B,) int, a row of
            `language`};
    language: {"input_ids": (k, tokens), "attention_mask": (k, tokens)}, the tokenised instructions.
    Returns {"observation": {image key: (1, 1, H, W, 3) uint8, "proprio": (1, 1, P) float32, "timestep_pad_mask":
    (1, 1) bool, "pad_mask_dict": {key: (1, 1) bool}}, "task": {"language_instruction": {name: (1, tokens)},
    "pad_mask_dict": {"language_instruction": (1,) bool}}, "action": (1, 1, horizon, A) float32}.
    """
    images = sorted(k for k in batch if k.startswith("image_"))
    if not images:
        raise ValueError("a training batch without an image_* key cannot give example frames")
    for key in images:
        shape = np.shape(batch[key])
        if len(shape) != 5 or shape[1] != 1 or shape[-1] != 3 or np.asarray(batch[key]).dtype != np.uint8:
            raise ValueError(f"{key}: expected (batch, 1, H, W, 3) uint8 frames, got {shape} "
                             f"{np.asarray(batch[key]).dtype}")
    row = int(np.asarray(batch["instruction"])[0])
    observation = {key: np.asarray(batch[key][:1], np.uint8) for key in images}
    observation["proprio"] = np.asarray(batch["proprio"][:1], np.float32)
    observation["timestep_pad_mask"] = np.ones((1, 1), bool)
    observation["pad_mask_dict"] = {key: np.ones((1, 1), bool) for key in [*images, "proprio"]}
    return {
        "observation": observation,
        "task": {"language_instruction": {name: np.asarray(value[row:row + 1]) for name, value in language.items()},
                 "pad_mask_dict": {"language_instruction": np.ones((1,), bool)}},
        "action": np.asarray(batch["actions"][:1], np.float32)[:, None],
    }

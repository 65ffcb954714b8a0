"""The attention controls: an observation's camera frames without content (blank) or mirrored, so the model can be
asked the same step again (`--attention-controls blank,mirror --controls-every N`). Pure numpy, no files.

  blank    each frame of the window replaced by its own mean colour (no content at all)
  mirror   each frame of the window mirrored left-right (the content moves to the mirror-image patch)

The policy stores the readout attention of those passes (controls.npz); harness.analysis.position reads it back
(is a hot patch about the scene at all?).
"""

from __future__ import annotations

import numpy as np

CONTROL_NAMES = ("blank", "mirror")


def blank_frames(frames: np.ndarray) -> np.ndarray:
    """(..., H, W, 3) uint8 -> the same shape, each frame filled with its own mean colour (rounded)."""
    frames = np.asarray(frames)
    mean = frames.astype(np.float64).mean(axis=(-3, -2), keepdims=True)
    return np.broadcast_to(np.rint(mean).astype(frames.dtype), frames.shape).copy()


def mirror_frames(frames: np.ndarray) -> np.ndarray:
    """(..., H, W, 3) -> the same frames mirrored left-right (columns reversed); its own inverse."""
    return np.ascontiguousarray(np.asarray(frames)[..., ::-1, :])


CONTROLS = {"blank": blank_frames, "mirror": mirror_frames}


def parse_controls(spec: str | None) -> tuple[str, ...]:
    """'blank,mirror' -> ("blank", "mirror") in canonical order; an unknown or empty name is a one-line error."""
    names = [n.strip() for n in (spec or "").split(",")]
    if not spec or any(not n for n in names):
        raise ValueError(f"--attention-controls takes a comma-separated list of {', '.join(CONTROL_NAMES)}; got {spec!r}")
    unknown = sorted(set(names) - set(CONTROL_NAMES))
    if unknown:
        raise ValueError(f"--attention-controls: unknown control(s) {', '.join(unknown)}; use {', '.join(CONTROL_NAMES)}")
    return tuple(n for n in CONTROL_NAMES if n in names)


def control_observation(observation: dict, control: str) -> dict:
    """An observation window (image_* (window, H, W, 3) uint8, ...) with every camera's frames under `control`."""
    transform = CONTROLS[control]
    return {k: (transform(v) if k.startswith("image_") else v) for k, v in observation.items()}



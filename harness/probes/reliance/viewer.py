"""The reliance probe's viewer layer: the reliance map of a Rerun recording (issue 45): where the policy relies, over each camera, beside where it
looks (the attention overlays).

At a `--reliance-every` step the step record carries region reliance rows (harness.probes.reliance.measure: one per camera x
labelled region) and the env's masks of the frame the model saw. The map of a camera (`reliance_map`): every pixel
of the frame gets the `reliance_per_pixel` of the region it belongs to (the region's share of the chunk's change per
unit of area), regions drawn from the step's masks by measure.region_masks, resized to the frame (the partition the
rows were measured on, at the frame's resolution); 0 for a region without a row (the remainder that has pixels only
at the frame's resolution). A camera the policy did not use at that step (its shares null: the chunk hardly changed
whichever region was replaced) gets a map of zeros.

The layer (`layer_png`, entity camera/<obs key>/reliance): an RGBA PNG at the frame's size, colour through the
overlays' colormap over [0, the map's maximum], opacity proportional to the value (LAYER_ALPHA at the maximum,
transparent at 0: a region the policy does not rely on leaves the frame as it is), drawn above the frame and below
the target mask. It is logged at reliance steps only: between them Rerun's latest-at shows the map of the last
reliance step at or before the shown step (0, N, 2N, ... with --reliance-every N), drawn on that step's masks.

Row values are taken as reliance.jsonl stores them (`stored_rows`: harness.files.json_safe, 6 significant digits),
so a live recording and `octo-harness view`'s rebuild from the file (harness.probes.reliance.reader.rows_by_step) hold
the same scalars and maps.
"""

from __future__ import annotations

import io
from typing import Mapping, Sequence

import numpy as np
from PIL import Image

from harness.files import json_safe
from harness.probes.reliance.measure import region_masks
from harness.outputs.overlays import colorize
from harness.outputs.rerun_layout import entity

LAYER_ALPHA = 0.6  # opacity of the map's maximum; 0 is transparent


def stored_rows(reliance: Mapping | None) -> list[dict]:
    """A step record's `reliance` ({"rows": [...], "seconds"} or None) -> its rows as reliance.jsonl stores them."""
    return [json_safe(dict(row)) for row in (reliance or {}).get("rows", ())]


def reliance_map(masks: Mapping[str, np.ndarray | None], rows: Sequence[Mapping], size: tuple[int, int]) -> np.ndarray:
    """One camera at one step: masks {env mask name: (h, w) bool} (upright, as the step record holds them), rows the
    reliance rows of that camera and step, size (H, W) the frame -> (H, W) float32, each pixel the reliance per pixel
    of its region (0 without a row, or everywhere when the camera's shares are null)."""
    out = np.zeros(tuple(size), np.float32)
    if not rows or any(row.get("reliance_share") is None for row in rows):
        return out
    per_pixel = {row["region"]: float(row.get("reliance_per_pixel") or 0.0) for row in rows}
    for region, mask in region_masks(masks, tuple(size)).items():
        out[mask] = max(0.0, per_pixel.get(region, 0.0))
    return out


def layer_png(values: np.ndarray, cmap: str = "viridis") -> bytes:
    """values (H, W) float32 >= 0 -> PNG bytes, RGBA: colour cmap(value / max), alpha LAYER_ALPHA * value / max
    (all transparent when the maximum is 0)."""
    values = np.asarray(values, np.float32)
    rgba = np.zeros((*values.shape, 4), np.uint8)
    top = float(values.max()) if values.size else 0.0
    if top > 0:
        rgba[..., :3] = colorize(values, 0.0, top, cmap)
        rgba[..., 3] = np.round(255 * LAYER_ALPHA * np.clip(values / top, 0.0, 1.0)).astype(np.uint8)
    out = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(out, format="PNG", optimize=False, compress_level=6)
    return out.getvalue()


def reliance_layers(rows: Sequence[Mapping], frames: Mapping[str, np.ndarray], masks: Mapping | None,
                    cmap: str = "viridis") -> dict[str, bytes]:
    """One step's stored rows, frames {obs key: (H, W, 3)} and masks {obs key: {name: (h, w) bool}} -> {obs key:
    layer PNG} for every camera that has rows, a frame and masks (in the rows' camera order)."""
    by_camera: dict[str, list[Mapping]] = {}
    for row in rows:
        by_camera.setdefault(row["camera"], []).append(row)
    out = {}
    for cam, cam_rows in by_camera.items():
        named = (masks or {}).get(cam)
        if cam in frames and named:
            out[cam] = layer_png(reliance_map(named, cam_rows, np.shape(frames[cam])[:2]), cmap)
    return out


class RelianceLayer:
    """The reliance probe in the recording: camera/<obs key>/reliance (the map, latest-at keeps it until the next
    reliance step) and reliance/<obs key>/<region> (each region's share; not logged where the camera was not used),
    a note on the camera views, the share per region on the timeline and a line of the episode's header."""

    @staticmethod
    def camera_views(cam: str, payload) -> list:
        return []

    @staticmethod
    def camera_note(payload) -> str:
        return "reliance map over it"

    @staticmethod
    def plots(payload) -> list:
        import rerun.blueprint as rrb

        return [rrb.TimeSeriesView(origin="reliance", name="reliance share per region")]

    @staticmethod
    def header(payload) -> list[str]:
        return ["- coloured over the frames: the reliance map of the last --reliance-every step at or before the "
                "shown one (each region's reliance per pixel; transparent: not relied on)"]

    @staticmethod
    def log(recording, record, payload) -> None:
        rows = stored_rows(payload)  # as reliance.jsonl holds them
        for cam, layer in reliance_layers(rows, record.frames, record.masks, recording.options.cmap).items():
            recording.layer(entity("camera", cam, "reliance"), layer)
        for row in rows:
            if row.get("reliance_share") is not None:  # null: the camera was not used at this step
                recording.scalars(entity("reliance", row["camera"], row["region"]), float(row["reliance_share"]),
                                  [f"{row['region']} reliance share"])

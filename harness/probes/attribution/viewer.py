"""The attribution probe's viewer layer: attribution/<method>/<obs key>, each method's map drawn over the frame (each
over its own range) at the steps that carry maps, in a tab per method beside the camera's attention."""

from __future__ import annotations

import numpy as np

from harness.outputs.overlays import heatmap_overlays
from harness.outputs.rerun_layout import entity, overlay_base


class AttributionLayer:
    @staticmethod
    def camera_views(cam: str, payload) -> list:
        import rerun.blueprint as rrb

        return [rrb.Spatial2DView(origin=entity("attribution", method, cam), name=f"{cam} {method}")
                for method in sorted((payload.get("maps") or {}).keys())]

    @staticmethod
    def camera_note(payload) -> str:
        return ""

    @staticmethod
    def plots(payload) -> list:
        return []

    @staticmethod
    def header(payload) -> list[str]:
        return []

    @staticmethod
    def log(recording, record, payload) -> None:
        opts = recording.options
        for method, by_camera in (payload.get("maps") or {}).items():
            for cam, grid in by_camera.items():
                grid = np.asarray(grid, np.float32)
                if cam not in record.frames or not np.isfinite(grid).any():
                    continue
                shown = overlay_base(np.asarray(record.frames[cam]))
                drawn = heatmap_overlays(shown, grid[None], float(np.nanmin(grid)), float(np.nanmax(grid)),
                                         opts.alpha, opts.cmap, opts.interpolation)[0]
                recording.image(entity("attribution", method, cam), drawn)

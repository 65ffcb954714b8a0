"""The video sink: rollout.mp4 (OutputOptions.video) and rollout.gif (OutputOptions.gif), one frame per step.

Each frame has one row per video camera (OutputOptions.video_camera: every camera the model reads by default):
camera | attention overlay | captions, over a strip of every layer's map. The overlay is a layer's fused heads, the
attention rollout (video_attention="rollout") or an attribution map (its maps come with the records). Frames use
per-frame colour ranges. The encoders (harness.outputs.video) write to temporary names and move them into place when
they close, at the end of the episode.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from harness.measures.attention import camera_maps, fuse_heads
from harness.outputs.overlays import heatmap_overlay, video_frame
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink
from harness.outputs.video import GifWriter, Mp4Writer


class RolloutVideo(Sink):
    """rollout.mp4 and/or rollout.gif; made when either is asked for."""

    @classmethod
    def wanted(cls, options, viewer) -> bool:
        return options.video or options.gif

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        opts = self.options
        self.mp4 = Mp4Writer(self.dir / "rollout.mp4", fps=opts.fps) if opts.video else None
        self.gif = GifWriter(self.dir / "rollout.gif", fps=opts.fps, every=opts.gif_every) if opts.gif else None

    @property
    def encoders(self) -> list:
        return [e for e in (self.mp4, self.gif) if e is not None]

    def add(self, step: FinishedStep) -> None:
        frame = self.frame(step)
        for encoder in self.encoders:
            encoder.append(frame)

    def end(self) -> None:
        for encoder in self.encoders:
            encoder.close()

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        files = {}
        if self.mp4 is not None and self.mp4.frames:
            files["video"] = "rollout.mp4"
        if self.gif is not None and self.gif.seen:
            files["gif"] = "rollout.gif"
        return files

    def abort(self) -> None:
        for encoder in self.encoders:
            encoder.abort()

    def frame(self, step: FinishedStep) -> np.ndarray:
        """The step's video frame (height, width, 3) uint8."""
        opts, layout, record = self.options, step.layout, step.record
        shown_frames, overlays, strips, row_boxes, labels = [], [], [], [], []
        for cam in layout.video_cameras:
            fused = fuse_heads(step.maps[cam], opts.head_fusion, axis=1)  # (layers, rows, cols)
            if layout.video_layer is not None:
                shown = fused[layout.video_layer]
                what = f"layer {layout.video_layer} ({opts.head_fusion} of heads)"
            elif step.rollout is not None:
                shown = camera_maps(step.rollout.mean(axis=0), step.tokens, cam)
                what = "attention rollout"
            else:  # an attribution method (OutputOptions checked the name)
                by_camera = (record.probes.get("attribution", {}).get("maps") or {}).get(opts.video_attention)
                if by_camera is None or cam not in by_camera:
                    raise ValueError(f"video_attention={opts.video_attention!r} needs its maps in the records: run with "
                                     f"--attribution {opts.video_attention}")
                shown = np.asarray(by_camera[cam], np.float32)
                what = f"{opts.video_attention} attribution"
            shown_frames.append(step.frames[cam])
            overlays.append(heatmap_overlay(step.frames[cam], shown, alpha=opts.alpha, cmap=opts.cmap,
                                            interpolation=opts.overlay_interpolation))
            strips.append(fused)
            row_boxes.append(step.boxes.get(cam))
            labels.append(f"{cam}: {what}; below: every layer")
        action = np.asarray(record.action_executed, np.float32)
        meta = self.meta
        captions = [
            f"{meta.task} | episode {meta.episode} | step {record.step}",
            labels[0],
            f"colours: {opts.cmap}, each map from its own min to its max",
            "action: " + " ".join(f"{a:+.3f}" for a in action),
            f"reward {float(record.reward):.3f} | success {'YES' if record.success else 'no'}",
            f'"{meta.instruction}"',
            f"RANDOM WEIGHTS: {meta.model}" if meta.model_is_random else f"model: {meta.model}",
        ]
        return video_frame(shown_frames, overlays, strips, captions, cmap=opts.cmap, alpha=opts.alpha, box=row_boxes,
                           labels=labels[1:], interpolation=opts.overlay_interpolation)

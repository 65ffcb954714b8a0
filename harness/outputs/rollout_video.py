"""The video sink: rollout.mp4 (OutputOptions.video) and rollout.gif (OutputOptions.gif), one frame per step.

Each frame has one row per video camera (OutputOptions.video_camera: every camera the model reads by default):
camera | attention overlay | captions, over a strip of every layer's map. The overlay is a layer's fused heads, the
attention rollout (video_attention="rollout") or an attribution map (its maps come with the records). Frames use
per-frame colour ranges. A policy without attention (FinishedStep.attention None) gets frames of its cameras beside
the captions only (`frames_only`: no overlay panels, no layer strips). The encoders (harness.outputs.video) write to temporary names and move them into place when
they close, at the end of the episode.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from harness.measures.attention import camera_maps, fuse_heads
from PIL import Image, ImageDraw

from harness.outputs.overlays import BACKGROUND, PAD, _draw_video_text, _round_up, heatmap_overlay, resize_nearest, video_frame
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
        if step.attention is None:  # a policy without attention: its frames and the captions
            return frames_only([step.frames[cam] for cam in layout.video_cameras], self.captions(
                record, f"{layout.video_cameras[0]}: the policy gives no attention (no overlay)", with_colours=False),
                [f"{cam}" for cam in layout.video_cameras[1:]])
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
        captions = self.captions(record, labels[0])
        return video_frame(shown_frames, overlays, strips, captions, cmap=opts.cmap, alpha=opts.alpha, box=row_boxes,
                           labels=labels[1:], interpolation=opts.overlay_interpolation)

    def captions(self, record, label: str, with_colours: bool = True) -> list[str]:
        """The text beside the first row: task, step, what the row shows, colours, action, reward, instruction, model."""
        action = np.asarray(record.action_executed, np.float32)
        meta = self.meta
        return [
            f"{meta.task} | episode {meta.episode} | step {record.step}",
            label,
            *([f"colours: {self.options.cmap}, each map from its own min to its max"] if with_colours else []),
            "action: " + " ".join(f"{a:+.3f}" for a in action),
            f"reward {float(record.reward):.3f} | success {'YES' if record.success else 'no'}",
            f'"{meta.instruction}"',
            f"RANDOM WEIGHTS: {meta.model}" if meta.model_is_random else f"model: {meta.model}",
        ]


def frames_only(frames: list[np.ndarray], captions: list[str], labels: list[str] = (), display: int = 256) -> np.ndarray:
    """A video frame without attention: one row per camera, [camera frame | text] (the first row's frame fills the
    top-left `display` x w pixels, as in `video_frame`); the size is padded to multiples of 16. (H, W, 3) uint8."""
    widths = [max(1, int(round(display * f.shape[1] / f.shape[0]))) for f in frames]
    column = max(widths)
    canvas = np.full((_round_up(len(frames) * (display + PAD), 16), _round_up(2 * column + 3 * PAD, 16), 3), BACKGROUND,
                     np.uint8)
    texts = []
    for r, (frame, width) in enumerate(zip(frames, widths)):
        top = r * (display + PAD)
        canvas[top:top + display, :width] = resize_nearest(np.asarray(frame, np.uint8), display, width)
        lines = list(captions) if r == 0 else ([labels[r - 1]] if r - 1 < len(labels) else [])
        texts.append((column + 2 * PAD, top, column, lines))
    image = Image.fromarray(canvas)
    _draw_video_text(ImageDraw.Draw(image), [], texts, display)
    return np.asarray(image)

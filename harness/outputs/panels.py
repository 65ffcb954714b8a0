"""The PNG sink: per-layer attention panels and attribution panels of selected steps.

  step_<tttt>_layer_<ll>.png    one panel per selected step (every OutputOptions.png_every-th) and layer: rows =
                                cameras, columns = heads and the fused head, colour bars, optional target box
  step_<tttt>_attribution.png   at those steps when they carry attribution maps: rows = cameras, columns = methods

PNGs are encoded by `encode_png` (numpy + zlib, which releases the GIL) in a small thread pool
(`OutputOptions.png_workers`), so the control loop's Python code keeps running while panels compress. With
normalisation "episode" the colour range of each (layer, camera) is the whole episode's, known only at the end, so
those panels are rendered in `end()`.
"""

from __future__ import annotations

import struct
import time
import zlib
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

from harness.measures.attention import fuse_heads
from harness.files import write_atomic
from harness.outputs.overlays import attribution_panel, layer_panel
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink

PNG_NAME = "step_{step:04d}_layer_{layer:02d}.png"
ATTRIBUTION_PNG_NAME = "step_{step:04d}_attribution.png"  # every method side by side, at PNG steps that carry maps


def encode_png(image: np.ndarray, level: int = 2) -> bytes:
    """image (H, W, 3) uint8 -> PNG file bytes (8-bit RGB, 'Up' filter on every row, zlib `level`).

    Plain numpy + zlib rather than Pillow: zlib releases the GIL while compressing (Pillow's PNG
    encoder holds it), so encoding in the background does not stall the control loop and several
    PNGs compress in parallel. The Up filter (row minus the row above, mod 256) is one vectorised
    subtraction and compresses rendered frames and heatmaps well.
    """
    image = np.ascontiguousarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"PNG images must be (height, width, 3) uint8; got {image.shape} {image.dtype}")
    height, width = image.shape[:2]
    rows = image.reshape(height, width * 3)
    filtered = np.empty((height, width * 3 + 1), np.uint8)  # each row: filter byte, then filtered bytes
    filtered[:, 0] = 2  # filter type Up
    filtered[0, 1:] = rows[0]  # the row above the first is zero
    np.subtract(rows[1:], rows[:-1], out=filtered[1:, 1:])  # uint8 arithmetic wraps mod 256

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)  # 8 bits, truecolour, deflate, no interlace
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(filtered.tobytes(), level)) + chunk(b"IEND", b"")


class PngPanels(Sink):
    """The panels of every OutputOptions.png_every-th step (always made: with png_every 0 it writes none and still
    reports png_count 0 and the pattern)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        workers = self.options.png_workers
        self.pool = ThreadPoolExecutor(workers, thread_name_prefix="png") if workers else None
        self.pending: list[Future] = []  # oldest first; bounded so rendered panels do not pile up
        self.seconds: list[float] = []  # encode + write time of each PNG (in the pool)
        self.names: list[str] = []
        self.layout = None
        self.deferred: list[tuple] = []  # episode normalisation: (step, frames, maps, boxes) rendered at the end
        self.ranges: dict[tuple[int, str], list[float]] = {}  # (layer, camera) -> [min, max] over the episode

    def add(self, step: FinishedStep) -> None:
        opts, layout = self.options, step.layout
        self.layout = layout
        if opts.png_every and step.step % opts.png_every == 0:
            if opts.normalisation == "frame":
                for layer in layout.png_layers:
                    self.save_panel(step.step, layer, step.frames, {c: m[layer] for c, m in step.maps.items()},
                                    step.boxes, None)
            else:
                selected = {c: m[list(layout.png_layers)] for c, m in step.maps.items()}
                self.deferred.append((step.step, step.frames, selected, step.boxes))
            by_method = step.record.probes.get("attribution", {}).get("maps")
            if by_method:
                self.save_attribution_panel(step.step, step.frames, by_method, step.boxes)
        if opts.normalisation == "episode":
            for cam, m in step.maps.items():
                for layer in layout.png_layers:
                    stack = np.concatenate([m[layer], fuse_heads(m[layer], opts.head_fusion, axis=0)[None]])
                    lo, hi = self.ranges.setdefault((layer, cam), [np.inf, -np.inf])
                    self.ranges[(layer, cam)] = [min(lo, float(stack.min())), max(hi, float(stack.max()))]

    def end(self) -> None:
        layers = self.layout.png_layers if self.layout else ()
        for step, frames, selected, boxes in self.deferred:
            for i, layer in enumerate(layers):
                ranges = {cam: tuple(self.ranges[(layer, cam)]) for cam in selected}
                self.save_panel(step, layer, frames, {c: m[i] for c, m in selected.items()}, boxes, ranges)
        self.deferred = []
        self.drain(0)
        if self.pool is not None:
            self.pool.shutdown(wait=True)

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        files: dict[str, Any] = {"png_count": len(self.names), "png_pattern": PNG_NAME}
        if any(n.endswith("_attribution.png") for n in self.names):
            files["attribution_png_pattern"] = ATTRIBUTION_PNG_NAME
        return files

    def abort(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)

    def timings(self) -> dict[str, Any]:
        return {"png_encode": {"total": float(np.sum(self.seconds)), "count": len(self.seconds)}}

    def caption(self, step: int, layer: int) -> dict:
        note = f"RANDOM WEIGHTS ({self.meta.model})" if self.meta.model_is_random else self.meta.model
        return {"task": f"{self.meta.task} ep {self.meta.episode}", "step": step, "layer": layer, "note": note}

    def save_panel(self, step, layer, frames, maps, boxes, ranges) -> None:
        opts = self.options
        panel = layer_panel(
            frames, maps, self.caption(step, layer), ranges=ranges, boxes=boxes,
            head_fusion=opts.head_fusion, cmap=opts.cmap, alpha=opts.alpha, interpolation=opts.overlay_interpolation,
        )
        self.write_png(PNG_NAME.format(step=step, layer=layer), panel)

    def save_attribution_panel(self, step, frames, by_method, boxes) -> None:
        opts = self.options
        shown = {m: {cam: v for cam, v in by.items() if cam in frames} for m, by in by_method.items()}
        shown = {m: by for m, by in shown.items() if by}
        if not shown:  # maps only of cameras this episode has no frame for
            return
        panel = attribution_panel(frames, shown, self.caption(step, -1), boxes=boxes, cmap=opts.cmap, alpha=opts.alpha,
                                  interpolation=opts.overlay_interpolation)
        self.write_png(ATTRIBUTION_PNG_NAME.format(step=step), panel)

    def write_png(self, name: str, panel: np.ndarray) -> None:
        opts = self.options
        path, level = self.dir / name, opts.png_compress_level

        def save() -> None:
            start = time.perf_counter()
            write_atomic(path, lambda f: f.write(encode_png(panel, level)))
            self.seconds.append(time.perf_counter() - start)

        if self.pool is None:
            save()
        else:
            self.pending.append(self.pool.submit(save))
            self.drain(4 * opts.png_workers)
        self.names.append(name)

    def drain(self, keep: int) -> None:
        """Wait for the oldest PNG jobs until at most `keep` are pending; re-raises their errors."""
        while len(self.pending) > keep:
            self.pending.pop(0).result()

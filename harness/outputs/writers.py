"""Episode outputs: the sinks that turn per-step records into files, in a background thread.

`EpisodeWriter` receives `StepRecord`s from the control loop (`add_step` only enqueues) and, in its
own thread, computes the step's attention metrics, renders per-layer PNG panels and appends a frame
to the rollout video. `finish()` writes the arrays and JSON. Files in `episode_dir`:

  step_<tttt>_layer_<ll>.png  one panel per selected step and layer (step zero-padded to 4 digits,
                              layer to 2, e.g. step_0003_layer_11.png): rows = cameras, columns =
                              heads and the fused head, colour bars, optional target box
  step_<tttt>_attribution.png at PNG steps that carry attribution maps (--attribution, --faithfulness-every):
                              rows = cameras, columns = methods, each map coloured over its own range
  rollout.mp4 (rollout.gif)   one row per camera (OutputOptions.video_camera: every camera the model reads by
                              default): camera | attention overlay | captions, over a per-layer strip
  episode.rrd                 with OutputOptions.rerun: the episode as a Rerun recording (harness.outputs.rerun_sink)
  attention.npz               readout_attention (steps, layers, heads, readouts, keys) float16,
                              tokens/* (TokenMap.to_arrays), metrics/<name> (steps, ...) float32,
                              step (steps,), rollout_readout (steps, readouts, keys) float16 if used,
                              mask_fraction/<obs>/<name> (steps, rows, cols) float32: each patch's
                              coverage by the mask (attention.mask_fractions; nan where a step lacks it),
                              so mask mass can be recomputed per head / layer from readout_attention;
                              measures/layer/<m> (steps, layers), measures/head/<m> (steps, layers, heads)
                              float32: shares, entropy, mask mass and lift per step (analysis.aggregate);
                              phase (steps,) int8 index into phase_names (-1: none) for tasks with phases
  actions.npz                 predicted (steps, horizon, dim), executed (steps, dim), reward, success, step,
                              inferred (steps,) bool, input_hash/<key> (steps,) uint64: a 64-bit digest of what
                              the policy was fed at each step (harness.policy.input_digest of its resized image
                              or low-dim input), so two runs can tell for how many steps they saw the same inputs
  inputs.npz                  with record_inputs: input/<key> (steps, H, W, 3) uint8 / (steps, dims) float32, the
                              newest history entry the policy was fed at each step (env convention), step, inferred,
                              seed, instruction: `octo-harness replay` rebuilds every observation window from it
  metrics.jsonl               one JSON object per step: run, task, episode, step, reward, success, shares, entropy,
                              mask mass per layer, timings; every row has the same keys (null where n/a); "phase"
                              (the task phase of the state the model saw, envs.phases) for tasks with phases
  controls.npz                with --attention-controls, at the control steps: step (n,), <control>
                              (n, layers, heads, readouts, keys) float16 readout attention of the same inference on
                              the control frames (blank: each frame its mean colour; mirror: mirrored left-right)
  episode.json                metadata and summary; written LAST, so a directory holding it is complete

Every file is written to `<name>.tmp.<pid>.<ext>` in the same directory and moved into place with
os.replace; `abort()` (or an exception inside `with EpisodeWriter(...)`) deletes temporaries and
never writes episode.json. Starting a writer removes a stale episode.json from the directory.

PNGs are encoded by `encode_png` (numpy + zlib, which releases the GIL) in a small thread pool
(`png_workers`), so the control loop's Python code keeps running while panels compress.

Normalisation: "frame" colours each PNG row with that step's range; "episode" uses the range of
the whole episode per (layer, camera), which is known only at the end, so in that mode the PNGs
are rendered during `finish()`. The video always uses per-frame ranges. Exceptions raised in the
background thread are re-raised (as WriterError) by the next `add_step` or `finish`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import queue
import struct
import threading
import time
import zlib
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from harness.analysis.aggregate import measure_arrays
from harness.analysis.attention import HEAD_FUSIONS, camera_maps, fuse_heads, mask_fractions, rollout_readout_rows, step_metrics
from harness.octo.tokens import TokenMap
from harness.outputs.overlays import (attribution_panel, check_interpolation, colormap_lut, heatmap_overlay, layer_panel,
                                      mask_bbox, video_frame)
from harness.policy import input_digest
from harness.records import EpisodeMeta, StepRecord
from harness.files import atomic_write_json, json_safe, write_atomic
from harness.options import camera_list, layer_list, option, record
from harness.outputs.video import GifWriter, Mp4Writer

PNG_NAME = "step_{step:04d}_layer_{layer:02d}.png"
ATTRIBUTION_PNG_NAME = "step_{step:04d}_attribution.png"  # every method side by side, at PNG steps that carry maps
_STOP = object()


ATTRIBUTION_VIDEO = ("grad-attention", "saliency", "occlusion")  # attribution maps the MP4 can show (--video-attention)


def parse_video_attention(text: str):
    """--video-attention's text -> a layer index, 'rollout' or an attribution method of ATTRIBUTION_VIDEO."""
    import argparse

    if text in ("rollout", *ATTRIBUTION_VIDEO):
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--video-attention takes a layer index, 'rollout' or one of "
                                         f"{', '.join(ATTRIBUTION_VIDEO)}, got {text!r}") from None


class WriterError(RuntimeError):
    """The background writer failed; the cause is chained."""


@dataclass(frozen=True)
class OutputOptions:
    # PNG panels every n-th step; 0 = none
    png_every: int = option(1, "--png-every", "write overlays every n-th step (0 = none) [1]", type=int, file=(int,))
    # layers to render as PNG (negative counts from the end); None = all
    layers: tuple[int, ...] | None = option(None, "--layers", "overlay layers, e.g. 0,5,11 [all]", file=(str, list),
                                            convert=layer_list)
    video: bool = option(True, "--no-video", {"robustness": "no rollout.mp4 per episode"}, file=(bool,),
                         action="store_true", convert=lambda v: not v,
                         doc="no rollout.mp4")  # write rollout.mp4
    # overlay in the video: a layer index, "rollout" (needs full attention) or an attribution method of ATTRIBUTION_VIDEO
    # (its maps come with the records: the run computes them, --attribution)
    video_attention: str | int = option(
        -1, "--video-attention", "attention shown in the MP4: a layer index (default -1 = last), 'rollout', or an "
        "attribution map: grad-attention, saliency, occlusion (computed at every step, as --attribution)",
        type=parse_video_attention, file=(int, str),
        doc="attention shown in the MP4: a layer index (default `-1`, last), `rollout` (attention rollout; captures "
            "full matrices, slower), or an attribution map: `grad-attention`, `saliency`, `occlusion` (computed at "
            "every step, see [faithfulness](faithfulness.md))")
    # observation key(s) shown in the video, one row each (--video-cameras); None = every camera the model reads, in
    # the model's order (a single key, as older protocols hold it, is one row)
    video_camera: str | tuple[str, ...] | None = option(
        None, "--video-cameras", "cameras shown in the MP4, one row each (frame | overlay), e.g. image_primary or "
        "image_primary,image_wrist [all: every camera the model reads]", file=(str, list), metavar="KEYS",
        convert=camera_list)
    gif: bool = option(False, "--gif", "also write rollout.gif", file=(bool,), action="store_true",
                       convert=bool)  # every gif_every-th frame, half size
    gif_every: int = 2
    normalisation: str = option(  # PNG colour range: "frame" (this step) or "episode" (rendered at finish)
        "frame", "--normalisation", "[frame]", file=(str,), choices=("frame", "episode"),
        doc="heatmap colour range per frame or per episode [frame]")
    bbox: bool = option(True, "--bbox", "draw the target object's bounding box on overlays", file=(bool,),
                        action="store_true", convert=bool, absent=False)  # draw the target mask's bounding box
    fps: float = 10.0
    head_fusion: str = "mean"  # the fused-head column / video map: "mean", "max" or "min"
    cmap: str = "jet"
    alpha: float = 0.5  # heatmap weight in overlays
    queue_size: int = 4  # steps waiting for the writer before add_step blocks
    png_compress_level: int = 2  # zlib level 0-9 (low: fast, larger files)
    png_workers: int = 2  # threads compressing PNGs in parallel (zlib releases the GIL); 0 = in the writer thread
    record_inputs: bool = option(  # write inputs.npz: the policy's inputs at every step, for `octo-harness replay`
        False, "--record-inputs", "write each episode's policy inputs (inputs.npz: resized frames, proprio, seed, "
        "instruction; compressed) so `octo-harness replay` can run any model open loop on them", file=(bool,),
        action="store_true", convert=bool)
    overlay_interpolation: str = option(  # how patch maps are enlarged in PNGs, MP4 and recording: nearest | bilinear
        "nearest", "--overlay-interpolation", "how patch-grid maps are enlarged in PNGs, MP4 and recording: nearest "
        "(the honest patch grid) or bilinear (smooth, as the original attention-visualisation scripts) [nearest]",
        file=(str,), choices=("nearest", "bilinear"), sparse=True)
    # write episode.rrd, a Rerun recording of the episode (--rerun save; needs the viewer extra); the live modes
    # (spawn, serve) are chosen on the command line only (harness/cli/run.py)
    rerun: bool = option(
        False, "--rerun", "Rerun recording of every episode (pip install 'octo-harness[viewer]'): save writes "
        "episode.rrd beside its files (part of the protocol); spawn streams live to a viewer on this machine; serve "
        "hosts the web viewer for a headless server and prints its URL once (save,spawn / save,serve: both); see "
        "docs/viewer.md", file=(bool,), metavar="save|spawn|serve", convert=bool, sparse=True)

    def to_dict(self) -> dict:
        """The fields as plain data; the options added since protocols were first hashed only when not at their
        default (protocols that do not use them keep their hash and their run name)."""
        return record(self)

    def __post_init__(self) -> None:
        if self.png_every < 0:
            raise ValueError(f"png_every must be >= 0 (0 = no PNGs); got {self.png_every}")
        if self.layers is not None:
            object.__setattr__(self, "layers", tuple(int(layer) for layer in self.layers))
        if isinstance(self.video_attention, str) and self.video_attention.lstrip("-").isdigit():
            object.__setattr__(self, "video_attention", int(self.video_attention))  # "11" from a command line
        if not (self.video_attention in ("rollout", *ATTRIBUTION_VIDEO) or isinstance(self.video_attention, int)):
            raise ValueError(f"video_attention must be a layer index, 'rollout' or one of {', '.join(ATTRIBUTION_VIDEO)}; "
                             f"got {self.video_attention!r}")
        if self.normalisation not in ("frame", "episode"):
            raise ValueError(f"normalisation must be 'frame' or 'episode'; got {self.normalisation!r}")
        if self.head_fusion not in HEAD_FUSIONS:
            raise ValueError(f"head_fusion must be one of {HEAD_FUSIONS}; got {self.head_fusion!r}")
        if self.fps <= 0 or self.gif_every < 1 or self.queue_size < 1 or self.png_workers < 0:
            raise ValueError("fps must be > 0, gif_every >= 1, queue_size >= 1 and png_workers >= 0")
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1]; got {self.alpha}")
        if not 0 <= self.png_compress_level <= 9:
            raise ValueError(f"png_compress_level must be 0..9; got {self.png_compress_level}")
        colormap_lut(self.cmap)  # unknown colormap: clear error now, not in the thread
        check_interpolation(self.overlay_interpolation)
        if isinstance(self.video_camera, (list, tuple)):
            cameras = tuple(str(c) for c in self.video_camera)
            if not cameras or len(set(cameras)) < len(cameras):
                raise ValueError(f"video cameras must be distinct observation keys, at least one; got {list(cameras)}")
            object.__setattr__(self, "video_camera", cameras)

    @property
    def video_cameras(self) -> tuple[str, ...] | None:
        """The cameras chosen for the video rows (None: every camera the model reads)."""
        return (self.video_camera,) if isinstance(self.video_camera, str) else self.video_camera


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


def _stack_steps(per_step: list[dict[str, np.ndarray]], prefix: str) -> dict[str, np.ndarray]:
    """[{name: (...)} per step] -> {prefix + name: (steps, ...) float32}; steps that lack a name hold nan."""
    names: dict[str, tuple] = {}
    for m in per_step:
        for k, v in m.items():
            names.setdefault(k, np.shape(v))
    out = {}
    for name, shape in names.items():
        rows = [np.asarray(m[name], np.float32) if name in m else np.full(shape, np.nan, np.float32) for m in per_step]
        out[prefix + name] = np.stack(rows)
    return out


def _nest(flat: dict[str, Any]) -> dict[str, Any]:
    """{"a/b/c": v} -> {"a": {"b": {"c": v}}}."""
    out: dict[str, Any] = {}
    for key, value in flat.items():
        *parents, leaf = key.split("/")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out


def _scaled_box(mask: np.ndarray | None, frame: np.ndarray) -> tuple[int, int, int, int] | None:
    """Bounding box of a mask, in the pixels of `frame` (the mask may be at camera resolution)."""
    box = mask_bbox(mask)
    if box is None:
        return None
    sy = frame.shape[0] / mask.shape[0]
    sx = frame.shape[1] / mask.shape[1]
    y0, x0, y1, x1 = box
    return int(y0 * sy), int(x0 * sx), max(int(y0 * sy) + 1, round(y1 * sy)), max(int(x0 * sx) + 1, round(x1 * sx))


@dataclass
class _Layout:
    """What the first step fixes for the whole episode."""

    layers: int
    heads: int
    png_layers: tuple[int, ...]
    cameras: tuple[str, ...]  # observation keys with an image group and a frame
    video_cameras: tuple[str, ...]  # the video's rows
    video_layer: int | None  # None when the video shows the rollout


class EpisodeWriter:
    """Writes one episode's outputs from `StepRecord`s in a background thread (see the module docstring).

    Use as a context manager, or call `finish(summary)` on success and `abort()` on failure.
    """

    def __init__(self, episode_dir: str | os.PathLike, tokens: TokenMap | None, meta: EpisodeMeta,
                 options: OutputOptions | None = None, viewer: str | None = None):
        """tokens: the token map of the attention; a record's own `StepRecord.tokens` (the map of the
        inference that produced it) takes precedence, so None is fine when the records carry one.
        viewer: gRPC url of a live Rerun viewer to stream the episode to (harness.outputs.rerun_sink.start_viewer)."""
        self.dir = Path(episode_dir)
        self.tokens = tokens
        self.meta = meta
        self.options = options or OutputOptions()
        self.dir.mkdir(parents=True, exist_ok=True)
        (self.dir / "episode.json").unlink(missing_ok=True)  # the directory is incomplete until finish()

        self._queue: queue.Queue = queue.Queue(maxsize=self.options.queue_size)
        self._error: BaseException | None = None
        self._error_step: int | None = None
        self._aborting = threading.Event()
        self._done = False
        self._layout: _Layout | None = None
        self._mp4 = Mp4Writer(self.dir / "rollout.mp4", fps=self.options.fps) if self.options.video else None
        self._gif = (
            GifWriter(self.dir / "rollout.gif", fps=self.options.fps, every=self.options.gif_every) if self.options.gif else None
        )
        # the Rerun recording (harness.outputs.rerun_sink): episode.rrd with options.rerun, and/or a live viewer's url
        self._rerun = None
        if self.options.rerun or viewer is not None:
            from harness.outputs.rerun_sink import RRD_NAME, RerunSink, SinkOptions

            (self.dir / RRD_NAME).unlink(missing_ok=True)  # never a stale recording beside a new episode
            self._rerun = RerunSink(
                meta, SinkOptions(cmap=self.options.cmap, alpha=self.options.alpha, head_fusion=self.options.head_fusion,
                                  interpolation=self.options.overlay_interpolation),
                save=self.dir / RRD_NAME if self.options.rerun else None, connect=viewer,
                intervention=bool(meta.extra.get("intervention")), control_hz=meta.extra.get("control_hz"))
        # accumulated per step (background thread only, read after join)
        self._steps: list[int] = []
        self._attention: list[np.ndarray] = []  # (layers, heads, readouts, keys) float16
        self._rollout: list[np.ndarray] = []  # (readouts, keys) float16
        self._predicted: list[np.ndarray] = []
        self._executed: list[np.ndarray] = []
        self._rewards: list[float] = []
        self._success: list[bool] = []
        self._metrics: list[dict[str, np.ndarray]] = []
        self._mask_fractions: list[dict[str, np.ndarray]] = []  # "<obs>/<name>" -> (rows, cols) per step
        self._timings: list[dict[str, float]] = []
        self._attribution: list[tuple[int, dict]] = []  # (step, Probe result) at steps that carry one
        self._inferred: list[bool] = []
        self._phases: list[str | None] = []  # the task phase of each step's state
        self._controls: list[tuple[int, dict]] = []  # (step, {control: (layers, heads, readouts, keys)}) at control steps
        self._input_hashes: list[dict[str, int]] = []  # obs key -> input_digest per step
        self._inputs: list[dict[str, np.ndarray]] = []  # record_inputs: the policy's inputs per step
        self._pngs: list[str] = []
        self._deferred: list[tuple] = []  # episode normalisation: (step, frames, maps, boxes) rendered at finish
        self._ranges: dict[tuple[int, str], list[float]] = {}  # (layer, camera) -> [min, max] over the episode
        self._blocked: list[float] = []  # caller side: seconds each add_step waited for queue space
        workers = self.options.png_workers
        self._png_pool = ThreadPoolExecutor(workers, thread_name_prefix="png") if workers else None
        self._png_pending: list[Future] = []  # oldest first; bounded so rendered panels do not pile up
        self._png_seconds: list[float] = []  # encode + write time of each PNG (in the pool)
        self._rerun_seconds = 0.0  # logging the recording (in the writer thread)

        self._thread = threading.Thread(target=self._run, name=f"episode-writer-{meta.task}-{meta.episode}", daemon=True)
        self._thread.start()

    # ---- caller side -------------------------------------------------------------------------

    def add_step(self, record: StepRecord) -> float:
        """Enqueue a step for writing; blocks only while the queue is full. Returns the seconds blocked."""
        self._raise_if_failed()
        if self._done:
            raise RuntimeError("this episode writer is finished or aborted; create a new one for the next episode")
        start = time.perf_counter()
        self._put(record)
        blocked = time.perf_counter() - start
        self._blocked.append(blocked)
        return blocked

    def finish(self, summary: dict | None = None) -> dict:
        """Wait for the queue, write video, arrays, metrics and finally episode.json. Returns the summary written
        (with `episode_dir` and absolute `paths` added). `summary` entries override the computed ones
        (dict entries such as "timings" are merged key by key)."""
        if self._done:
            raise RuntimeError("this episode writer is already finished or aborted")
        start = time.perf_counter()
        try:
            self._put(_STOP)
            self._thread.join()
            self._raise_if_failed()
            files = self._write_files()
            if self._rerun is not None:
                files.update(self._finish_rerun(summary or {}))
            result = self._summary(files, summary or {}, time.perf_counter() - start)
            atomic_write_json(self.dir / "episode.json", result)
        except BaseException:
            self._abort_outputs()
            raise
        finally:
            self._done = True
        result["episode_dir"] = str(self.dir)
        result["paths"] = {name: str(self.dir / rel) for name, rel in files.items() if isinstance(rel, str)}
        return result

    def abort(self) -> None:
        """Stop the thread, drop queued steps and delete temporary files; episode.json is not written."""
        if self._done:
            return
        self._done = True
        self._aborting.set()
        while True:  # drop what is queued so the thread sees the stop marker promptly
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
        try:
            self._queue.put(_STOP, timeout=1.0)
        except queue.Full:
            pass
        self._thread.join(timeout=60)
        self._abort_outputs()

    def __enter__(self) -> "EpisodeWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()
        elif not self._done:
            self.finish()

    @property
    def blocked_seconds(self) -> list[float]:
        """Seconds each add_step call waited for queue space (the writer falling behind)."""
        return list(self._blocked)

    def _put(self, item) -> None:
        while True:
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                self._raise_if_failed()

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            where = f" at step {self._error_step}" if self._error_step is not None else ""
            raise WriterError(f"background writer failed{where}: {self._error!r}") from self._error

    def _abort_outputs(self) -> None:
        if self._png_pool is not None:
            self._png_pool.shutdown(wait=True, cancel_futures=True)
        for sink in (self._mp4, self._gif, self._rerun):
            if sink is not None:
                sink.abort()
        for tmp in self.dir.glob("*.tmp.*"):
            tmp.unlink(missing_ok=True)

    # ---- background thread -------------------------------------------------------------------

    def _run(self) -> None:
        step = None
        try:
            while True:
                item = self._queue.get()
                if item is _STOP:
                    break
                if self._aborting.is_set():  # abort(): drop remaining steps
                    continue
                step = item.step
                start = time.perf_counter()
                self._process(item)
                self._timings[-1]["write"] = time.perf_counter() - start
            step = None
            if not self._aborting.is_set():
                self._render_deferred()
                self._drain_png(0)
                if self._png_pool is not None:
                    self._png_pool.shutdown(wait=True)
                for sink in (self._mp4, self._gif):
                    if sink is not None:
                        sink.close()
        except BaseException as err:  # surfaced in the caller by add_step / finish
            self._error, self._error_step = err, step

    def _resolve_layout(self, record: StepRecord, attn: np.ndarray) -> _Layout:
        layers, heads = attn.shape[:2]
        opts = self.options

        def layer_index(i: int) -> int:
            if not -layers <= i < layers:
                raise ValueError(f"layer {i} is out of range for a model with {layers} layers; choose 0..{layers - 1}")
            return i % layers

        png_layers = tuple(range(layers)) if opts.layers is None else tuple(sorted({layer_index(i) for i in opts.layers}))
        cameras = tuple(key for _, key, _, _ in self.tokens.image_groups if key in record.frames)
        if not cameras and (opts.png_every or opts.video or opts.gif):
            raise ValueError(f"no frame for any camera of the model {[k for _, k, _, _ in self.tokens.image_groups]}; "
                             "put the frames the model saw in StepRecord.frames")
        video_cameras = opts.video_cameras or cameras
        unknown = [c for c in video_cameras if c not in cameras]
        if (opts.video or opts.gif) and unknown:
            raise ValueError(f"video camera(s) {unknown} have no frame or image group; choose from {list(cameras)}")
        video_layer = None if opts.video_attention in ("rollout", *ATTRIBUTION_VIDEO) else layer_index(int(opts.video_attention))
        return _Layout(layers, heads, png_layers, cameras, tuple(video_cameras), video_layer)

    def _process(self, record: StepRecord) -> None:
        if record.tokens is not None:
            if self._layout is None:
                self.tokens = record.tokens
            elif record.tokens.num_keys != self.tokens.num_keys:
                raise ValueError(f"step {record.step}: the token map changed from {self.tokens.num_keys} to "
                                 f"{record.tokens.num_keys} keys within the episode")
        if self.tokens is None:
            raise ValueError("no token map: pass tokens to EpisodeWriter or set StepRecord.tokens")
        tokens, opts = self.tokens, self.options
        attn = np.asarray(record.readout_attention, dtype=np.float32)  # (layers, heads, readouts, keys)
        if attn.ndim != 4 or attn.shape[-1] != tokens.num_keys:
            raise ValueError(f"readout_attention must be (layers, heads, readouts, keys={tokens.num_keys}); got {attn.shape}")
        if self._layout is None:
            self._layout = self._resolve_layout(record, attn)
        layout = self._layout
        if attn.shape[:2] != (layout.layers, layout.heads):
            raise ValueError(f"step {record.step}: attention has shape {attn.shape}, the episode started with "
                             f"{layout.layers} layers and {layout.heads} heads")

        self._steps.append(int(record.step))
        self._attention.append(attn.astype(np.float16))
        self._predicted.append(np.asarray(record.actions_predicted, np.float32))
        self._executed.append(np.asarray(record.action_executed, np.float32))
        self._rewards.append(float(record.reward))
        self._success.append(bool(record.success))
        self._metrics.append(step_metrics(attn, tokens, record.masks))
        if self._rerun is not None:
            start = time.perf_counter()
            self._rerun.log_step(record, tokens, self._metrics[-1])
            self._rerun_seconds += time.perf_counter() - start
        self._mask_fractions.append(mask_fractions(tokens, record.masks))
        self._timings.append({k: float(v) for k, v in record.timings.items()})
        if record.attribution is not None:
            self._attribution.append((record.step, record.attribution))
        self._phases.append(record.phase)
        if record.controls:
            for name, value in record.controls.items():
                if np.shape(value) != attn.shape:
                    raise ValueError(f"step {record.step}: control {name!r} attention has shape {np.shape(value)}, "
                                     f"the step's attention {attn.shape}")
            self._controls.append((record.step, {k: np.asarray(v, np.float32).astype(np.float16)
                                                 for k, v in record.controls.items()}))
        inputs = record.policy_inputs or {}
        self._inferred.append(bool(record.inferred))
        self._input_hashes.append({k: input_digest(v) for k, v in inputs.items()})
        if opts.record_inputs:
            if not inputs:
                raise ValueError("record_inputs needs the policy's inputs in every StepRecord (policy_inputs)")
            self._inputs.append(inputs)

        frames = {cam: record.frames[cam] for cam in layout.cameras}
        # cam -> (layers, heads, rows, cols): readouts averaged
        maps = {cam: camera_maps(attn, tokens, cam).mean(axis=2) for cam in layout.cameras}
        boxes = {}
        if opts.bbox and record.masks:
            for cam in layout.cameras:
                target = (record.masks.get(cam) or {}).get("target")
                if target is not None:
                    boxes[cam] = _scaled_box(np.asarray(target, bool), frames[cam])

        if opts.png_every and record.step % opts.png_every == 0:
            if opts.normalisation == "frame":
                for layer in layout.png_layers:
                    self._save_panel(record.step, layer, frames, {c: m[layer] for c, m in maps.items()}, boxes, None)
            else:
                selected = {c: m[list(layout.png_layers)] for c, m in maps.items()}
                self._deferred.append((record.step, frames, selected, boxes))
            by_method = (record.attribution or {}).get("maps")
            if by_method:
                self._save_attribution_panel(record.step, frames, by_method, boxes)
        if opts.normalisation == "episode":
            for cam, m in maps.items():
                for layer in layout.png_layers:
                    stack = np.concatenate([m[layer], fuse_heads(m[layer], opts.head_fusion, axis=0)[None]])
                    lo, hi = self._ranges.setdefault((layer, cam), [np.inf, -np.inf])
                    self._ranges[(layer, cam)] = [min(lo, float(stack.min())), max(hi, float(stack.max()))]

        rollout = None
        if opts.video_attention == "rollout":
            if record.full_attention is None:
                raise ValueError("video_attention='rollout' needs full attention matrices; "
                                 "request full attention from the policy or choose a layer index")
            rollout = rollout_readout_rows(record.full_attention, tokens, head_fusion=opts.head_fusion)  # (readouts, keys)
            self._rollout.append(rollout.astype(np.float16))
        if self._mp4 is not None or self._gif is not None:
            frame = self._video_frame(record, frames, maps, boxes, rollout)
            for sink in (self._mp4, self._gif):
                if sink is not None:
                    sink.append(frame)

    def _caption(self, step: int, layer: int) -> dict:
        note = f"RANDOM WEIGHTS ({self.meta.model})" if self.meta.model_is_random else self.meta.model
        return {"task": f"{self.meta.task} ep {self.meta.episode}", "step": step, "layer": layer, "note": note}

    def _save_panel(self, step, layer, frames, maps, boxes, ranges) -> None:
        opts = self.options
        panel = layer_panel(
            frames, maps, self._caption(step, layer), ranges=ranges, boxes=boxes,
            head_fusion=opts.head_fusion, cmap=opts.cmap, alpha=opts.alpha, interpolation=opts.overlay_interpolation,
        )
        self._write_png(PNG_NAME.format(step=step, layer=layer), panel)

    def _write_png(self, name: str, panel: np.ndarray) -> None:
        opts = self.options
        path, level = self.dir / name, opts.png_compress_level

        def save() -> None:
            start = time.perf_counter()
            write_atomic(path, lambda f: f.write(encode_png(panel, level)))
            self._png_seconds.append(time.perf_counter() - start)

        if self._png_pool is None:
            save()
        else:
            self._png_pending.append(self._png_pool.submit(save))
            self._drain_png(4 * opts.png_workers)
        self._pngs.append(name)

    def _save_attribution_panel(self, step, frames, by_method, boxes) -> None:
        opts = self.options
        shown = {m: {cam: v for cam, v in by.items() if cam in frames} for m, by in by_method.items()}
        shown = {m: by for m, by in shown.items() if by}
        if not shown:  # maps only of cameras this episode has no frame for
            return
        panel = attribution_panel(frames, shown, self._caption(step, -1), boxes=boxes, cmap=opts.cmap, alpha=opts.alpha,
                                  interpolation=opts.overlay_interpolation)
        self._write_png(ATTRIBUTION_PNG_NAME.format(step=step), panel)

    def _drain_png(self, keep: int) -> None:
        """Wait for the oldest PNG jobs until at most `keep` are pending; re-raises their errors."""
        while len(self._png_pending) > keep:
            self._png_pending.pop(0).result()

    def _render_deferred(self) -> None:
        layers = self._layout.png_layers if self._layout else ()
        for step, frames, selected, boxes in self._deferred:
            for i, layer in enumerate(layers):
                ranges = {cam: tuple(self._ranges[(layer, cam)]) for cam in selected}
                self._save_panel(step, layer, frames, {c: m[i] for c, m in selected.items()}, boxes, ranges)
        self._deferred = []

    def _video_frame(self, record, frames, maps, boxes, rollout) -> np.ndarray:
        opts, layout = self.options, self._layout
        shown_frames, overlays, strips, row_boxes, labels = [], [], [], [], []
        for cam in layout.video_cameras:
            fused = fuse_heads(maps[cam], opts.head_fusion, axis=1)  # (layers, rows, cols)
            if opts.video_attention in ATTRIBUTION_VIDEO:
                by_camera = ((record.attribution or {}).get("maps") or {}).get(opts.video_attention)
                if by_camera is None or cam not in by_camera:
                    raise ValueError(f"video_attention={opts.video_attention!r} needs its maps in the records: run with "
                                     f"--attribution {opts.video_attention}")
                shown = np.asarray(by_camera[cam], np.float32)
                what = f"{opts.video_attention} attribution"
            elif rollout is not None:
                shown = camera_maps(rollout.mean(axis=0), self.tokens, cam)
                what = "attention rollout"
            else:
                shown = fused[layout.video_layer]
                what = f"layer {layout.video_layer} ({opts.head_fusion} of heads)"
            shown_frames.append(frames[cam])
            overlays.append(heatmap_overlay(frames[cam], shown, alpha=opts.alpha, cmap=opts.cmap,
                                            interpolation=opts.overlay_interpolation))
            strips.append(fused)
            row_boxes.append(boxes.get(cam))
            labels.append(f"{cam}: {what}; below: every layer")
        action = np.asarray(record.action_executed, np.float32)
        captions = [
            f"{self.meta.task} | episode {self.meta.episode} | step {record.step}",
            labels[0],
            "action: " + " ".join(f"{a:+.3f}" for a in action),
            f"reward {float(record.reward):.3f} | success {'YES' if record.success else 'no'}",
            f'"{self.meta.instruction}"',
            f"RANDOM WEIGHTS: {self.meta.model}" if self.meta.model_is_random else f"model: {self.meta.model}",
        ]
        return video_frame(shown_frames, overlays, strips, captions, cmap=opts.cmap, alpha=opts.alpha, box=row_boxes,
                           labels=labels[1:], interpolation=opts.overlay_interpolation)

    # ---- files at finish ---------------------------------------------------------------------

    def _metric_arrays(self) -> dict[str, np.ndarray]:
        """metrics/<name> and mask_fraction/<obs>/<name> -> (steps, ...) float32; steps that lack one (e.g. no mask) hold nan."""
        return {**_stack_steps(self._metrics, "metrics/"), **_stack_steps(self._mask_fractions, "mask_fraction/")}

    def _write_files(self) -> dict[str, Any]:
        steps = np.asarray(self._steps, np.int32)
        files: dict[str, Any] = {}
        arrays = {"step": steps, **self.tokens.to_arrays(), **self._metric_arrays()}
        if self._attention:
            arrays["readout_attention"] = np.stack(self._attention)
            arrays.update(measure_arrays(arrays, self.tokens))  # per-head measures the report aggregates
        if self._rollout:
            arrays["rollout_readout"] = np.stack(self._rollout)
        names = self._phase_names()
        if names:
            arrays["phase"] = np.asarray([names.index(p) if p in names else -1 for p in self._phases], np.int8)
            arrays["phase_names"] = np.asarray(names)
        write_atomic(self.dir / "attention.npz", lambda f: np.savez(f, **arrays))
        files["attention"] = "attention.npz"

        actions = {
            "step": steps,
            "predicted": np.stack(self._predicted) if self._predicted else np.zeros((0, 0, 0), np.float32),
            "executed": np.stack(self._executed) if self._executed else np.zeros((0, 0), np.float32),
            "reward": np.asarray(self._rewards, np.float32),
            "success": np.asarray(self._success, bool),
            "inferred": np.asarray(self._inferred, bool),
            **{f"input_hash/{k}": np.asarray([h.get(k, 0) for h in self._input_hashes], np.uint64)
               for k in dict.fromkeys(k for h in self._input_hashes for k in h)},
        }
        write_atomic(self.dir / "actions.npz", lambda f: np.savez(f, **actions))
        files["actions"] = "actions.npz"
        if self.options.record_inputs:
            recorded = {f"input/{k}": np.stack([entry[k] for entry in self._inputs]) for k in self._inputs[0]} \
                if self._inputs else {}
            recorded.update(step=steps, inferred=np.asarray(self._inferred, bool), seed=np.asarray(self.meta.seed),
                            instruction=np.asarray(self.meta.instruction))
            write_atomic(self.dir / "inputs.npz", lambda f: np.savez_compressed(f, **recorded))
            files["inputs"] = "inputs.npz"

        # every row has the same keys (null where a metric or timing does not apply at that step), plus its ids
        metric_names = list(dict.fromkeys(k for m in self._metrics for k in m))
        timing_names = list(dict.fromkeys([k for t in self._timings for k in t] + (["blocked"] if self._blocked else [])))
        lines = []
        for i, step in enumerate(self._steps):
            timings = {**self._timings[i], **({"blocked": self._blocked[i]} if i < len(self._blocked) else {})}
            entry = {"run": self.meta.run, "task": self.meta.task, "episode": self.meta.episode, "step": step,
                     "reward": self._rewards[i], "success": self._success[i],
                     **({"phase": self._phases[i]} if names else {}),
                     **_nest({name: self._metrics[i].get(name) for name in metric_names}),
                     "timings": {name: timings.get(name) for name in timing_names}}
            lines.append(json.dumps(json_safe(entry)))
        write_atomic(self.dir / "metrics.jsonl", lambda f: f.write(("\n".join(lines) + "\n" if lines else "").encode()))
        files["metrics"] = "metrics.jsonl"
        if self._attribution:
            files.update(self._write_attribution())
        if self._controls:
            controls = {"step": np.asarray([s for s, _ in self._controls], np.int32)}
            for name in dict.fromkeys(k for _, c in self._controls for k in c):
                if any(name not in c for _, c in self._controls):
                    raise ValueError(f"control {name!r} is missing at some control steps")
                controls[name] = np.stack([c[name] for _, c in self._controls])
            write_atomic(self.dir / "controls.npz", lambda f: np.savez(f, **controls))
            files["controls"] = "controls.npz"

        if self._mp4 is not None and self._mp4.frames:
            files["video"] = "rollout.mp4"
        if self._gif is not None and self._gif.seen:
            files["gif"] = "rollout.gif"
        files["png_count"] = len(self._pngs)
        files["png_pattern"] = PNG_NAME
        if any(n.endswith("_attribution.png") for n in self._pngs):
            files["attribution_png_pattern"] = ATTRIBUTION_PNG_NAME
        return files

    def _phase_names(self) -> tuple[str, ...]:
        """The task's phases when any step recorded one (else ())."""
        if not any(p is not None for p in self._phases):
            return ()
        from envs.phases import phase_names

        names = phase_names(self.meta.task)
        unknown = sorted({p for p in self._phases if p is not None and p not in names})
        if unknown:
            raise ValueError(f"phases {unknown} are not phases of task {self.meta.task} ({', '.join(names) or 'none'})")
        return names

    def _finish_rerun(self, summary: dict) -> dict[str, str]:
        """Close the recording with the episode's outcome; episode.rrd when it was saved."""
        start = time.perf_counter()
        outcome = {"success": bool(summary.get("success", any(self._success))), "steps": len(self._steps),
                   "return": float(np.sum(self._rewards)) if self._steps else 0.0}
        for key in ("actions_clipped",):
            if key in summary:
                outcome[key] = summary[key]
        path = self._rerun.finish(outcome)
        self._rerun_seconds += time.perf_counter() - start
        return {"rerun": path.name} if path is not None else {}

    def _write_attribution(self) -> dict[str, str]:
        """attribution.npz: step (n,), map/<method>/<obs key> (n, rows, cols) float32 at the steps that carry maps;
        faithfulness.jsonl: one row per step x camera x method (harness.analysis.faithfulness), when measured."""
        files = {}
        steps = np.asarray([s for s, _ in self._attribution], np.int32)
        names = list(dict.fromkeys((m, k) for _, a in self._attribution for m, by in a["maps"].items() for k in by))
        arrays = {"step": steps, "seconds": np.asarray([a.get("seconds", np.nan) for _, a in self._attribution])}
        for method, key in names:
            arrays[f"map/{method}/{key}"] = np.stack([a["maps"][method][key] for _, a in self._attribution]).astype(np.float32)
        write_atomic(self.dir / "attribution.npz", lambda f: np.savez(f, **arrays))
        files["attribution"] = "attribution.npz"
        lines = [json.dumps(json_safe({"run": self.meta.run, "task": self.meta.task, "episode": self.meta.episode,
                                       "seed": self.meta.seed, "step": step, **row}))
                 for step, a in self._attribution for row in a.get("faithfulness", [])]
        if lines:
            write_atomic(self.dir / "faithfulness.jsonl", lambda f: f.write(("\n".join(lines) + "\n").encode()))
            files["faithfulness"] = "faithfulness.jsonl"
        return files

    def _summary(self, files: dict, summary: dict, finish_s: float) -> dict:
        n = len(self._steps)
        per_step: dict[str, list[float]] = {}
        for i, t in enumerate(self._timings):
            for k, v in t.items():
                per_step.setdefault(k, []).append(v)
            if i < len(self._blocked):
                per_step.setdefault("blocked", []).append(self._blocked[i])
        timings = {
            "total": {k: float(np.sum(v)) for k, v in per_step.items()},
            "mean": {k: float(np.mean(v)) for k, v in per_step.items()},
            "finish": finish_s,
            "png_encode": {"total": float(np.sum(self._png_seconds)), "count": len(self._png_seconds)},
            **({"rerun": self._rerun_seconds} if self._rerun is not None else {}),
        }
        layout = self._layout
        result = {
            **dataclasses.asdict(self.meta),
            "success": any(self._success),
            "steps": n,
            "return": float(np.sum(self._rewards)) if n else 0.0,
            "layers": layout.layers if layout else None,
            "heads": layout.heads if layout else None,
            "keys": self.tokens.num_keys,
            "timings": timings,
            "files": files,
            "options": dataclasses.asdict(self.options),
        }
        for key, value in summary.items():  # the caller's entries win; dicts (e.g. timings) are merged one level
            if isinstance(value, dict) and isinstance(result.get(key), dict):
                result[key] = {**result[key], **value}
            else:
                result[key] = value
        return result

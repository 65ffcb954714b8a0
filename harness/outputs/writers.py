"""Episode outputs: the sinks that turn per-step records into files, in a background thread.

`EpisodeWriter` receives `StepRecord`s from the control loop (`add_step` only enqueues) and, in its
own thread, finishes each into a `FinishedStep` (attention metrics, per-camera maps, target boxes:
harness.outputs.steps) and hands it to every sink of the table `harness.outputs.sinks.sink_table()`: one
sink per output, which renders PNG panels or appends a video frame as steps come and writes its
files when the episode closes. `finish()` closes the sinks and writes episode.json. Files in `episode_dir`:

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
                              float32: shares, entropy, mask mass and lift per step (measures.episode);
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

A policy without attention (StepRecord.readout_attention None: harness.policies.Capabilities.attention False, e.g. a
served policy) leaves out every attention part and writes the rest: attention.npz holds only step (and phase,
phase_names), the per-step index every finished episode records (harness.runfolder.integrity.RECORDED), with no
readout_attention, tokens/*, metrics/*, mask_fraction/* or measures/*; no step_*_layer_*.png (png_count 0);
rollout.mp4 shows each video camera's frame beside its captions, without overlay panels or layer strips;
metrics.jsonl rows have no attention measures; actions.npz and inputs.npz are as always; episode.rrd holds frames,
masks, actions and scalars. episode.json then says "attention": false, with layers, heads and keys null (an episode
with attention has no "attention" key: its files are byte for byte those of before).

Every file is written to `<name>.tmp.<pid>.<ext>` in the same directory and moved into place with
os.replace; `abort()` (or an exception inside `with EpisodeWriter(...)`) deletes temporaries and
never writes episode.json. Starting a writer removes a stale episode.json from the directory.

PNGs are encoded by `harness.outputs.panels.encode_png` (numpy + zlib, which releases the GIL) in a small thread pool
(`png_workers`), so the control loop's Python code keeps running while panels compress.

Normalisation: "frame" colours each PNG row with that step's range; "episode" uses the range of
the whole episode per (layer, camera), which is known only at the end, so in that mode the PNGs
are rendered during `finish()`. The video always uses per-frame ranges. Exceptions raised in the
background thread are re-raised (as WriterError) by the next `add_step` or `finish`.
"""

from __future__ import annotations

import dataclasses
import os
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from harness.measures.attention import HEAD_FUSIONS
from harness.files import atomic_write_json
from harness.octo.tokens import TokenMap
from harness.outputs.overlays import check_interpolation, colormap_lut
from harness.outputs.sinks import open_sinks
from harness.outputs.steps import EpisodeEnd, StepFinisher
from harness.records import EpisodeMeta, StepRecord
from harness.options import camera_list, layer_list, option, options, record

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


def saves_recording(value) -> bool:
    """--rerun MODES (or a protocol file's true / false) -> the `rerun` field: whether each episode's episode.rrd is
    saved, i.e. 'save' among the modes (spawn and serve are live viewers, chosen on the command line only)."""
    if isinstance(value, bool):
        return value
    from harness.outputs.rerun_sink import parse_modes

    return "save" in parse_modes(value)


class WriterError(RuntimeError):
    """The background writer failed; the cause is chained."""


@dataclass(frozen=True)
class OutputOptions:
    # PNG panels every n-th step; 0 = none
    png_every: int = option(1, "--png-every", "write overlays every n-th step (0 = none)", type=int, file=(int,))
    # layers to render as PNG (negative counts from the end); None = all
    layers: tuple[int, ...] | None = option(None, "--layers", "overlay layers, e.g. 0,5,11", file=(str, list),
                                            convert=layer_list, default_text="all")
    video: bool = option(True, "--no-video", {"robustness": "no rollout.mp4 per episode"}, file=(bool,),
                         action="store_true", negated=True,
                         doc="no rollout.mp4")  # write rollout.mp4
    # overlay in the video: a layer index, "rollout" (needs full attention) or an attribution method of ATTRIBUTION_VIDEO
    # (its maps come with the records: the run computes them, --attribution)
    video_attention: str | int = option(
        -1, "--video-attention", "attention shown in the MP4: a layer index (-1 = the last), 'rollout', or an "
        "attribution map: grad-attention, saliency, occlusion (computed at every step, as --attribution)",
        type=parse_video_attention, file=(int, str),
        doc="attention shown in the MP4: a layer index (default `-1`, last), `rollout` (attention rollout; captures "
            "full matrices, slower), or an attribution map: `grad-attention`, `saliency`, `occlusion` (computed at "
            "every step, see [faithfulness](faithfulness.md))")
    # observation key(s) shown in the video, one row each (--video-cameras); None = every camera the model reads, in
    # the model's order (a single key, as older protocols hold it, is one row)
    video_camera: str | tuple[str, ...] | None = option(
        None, "--video-cameras", "cameras shown in the MP4, one row each (frame | overlay), e.g. image_primary or "
        "image_primary,image_wrist", file=(str, list), metavar="KEYS", default_text="all: every camera the model reads",
        field="video_camera",
        convert=camera_list)
    gif: bool = option(False, "--gif", "also write rollout.gif", file=(bool,), action="store_true",
                       convert=bool)  # every gif_every-th frame, half size
    gif_every: int = 2
    normalisation: str = option(  # PNG colour range: "frame" (this step) or "episode" (rendered at finish)
        "frame", "--normalisation", "", file=(str,), choices=("frame", "episode"),
        doc="heatmap colour range per frame or per episode [frame]")
    bbox: bool = option(False, "--bbox", "draw the target object's bounding box on overlays", file=(bool,),
                        action="store_true", convert=bool)  # draw the target mask's bounding box
    fps: float = 10.0
    head_fusion: str = "mean"  # the fused-head column / video map: "mean", "max" or "min"
    # the overlays' colour map: presentation only, outside the protocol and its hash (recorded in the manifest's
    # "presentation"; a resume draws with the run's own), so a run made with another one still resumes
    cmap: str = option(
        "viridis", "--colormap", "colour map of the attention overlays (PNGs, MP4, report grids, viewer): a matplotlib "
        "name; viridis is perceptually uniform, jet the old look", file=(str,), field="cmap", hashed=False,
        metavar="NAME", doc="colour map of the attention overlays (PNGs, MP4, report grids, viewer): a matplotlib name, "
        "e.g. `inferno` or `jet` (whose bright bands invent edges); presentation only, outside the protocol's hash, "
        "and a resume draws with the run's own [viridis]")
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
        "(the honest patch grid) or bilinear (smooth, as the original attention-visualisation scripts)",
        file=(str,), choices=("nearest", "bilinear"), sparse=True)
    # write episode.rrd, a Rerun recording of the episode (--rerun save; needs the viewer extra): the flag takes modes,
    # the field holds whether 'save' is among them (saves_recording); the live modes (spawn, serve) are chosen on the
    # command line only (harness/cli/run.py)
    rerun: bool = option(
        False, "--rerun", "Rerun recording of every episode (pip install 'octo-harness[viewer]'): save writes "
        "episode.rrd beside its files (part of the protocol); spawn streams live to a viewer on this machine; serve "
        "hosts the web viewer for a headless server and prints its URL once (save,spawn / save,serve: both); see "
        "docs/viewer.md", file=(bool,), metavar="save|spawn|serve", convert=saves_recording, sparse=True)

    def to_dict(self) -> dict:
        """The fields as plain data; the options added since protocols were first hashed only when not at their
        default (protocols that do not use them keep their hash and their run name)."""
        data = record(self)
        for field, o in options(type(self)):
            if not o.hashed:  # presentation (the colour map): recorded beside the protocol, not in it
                data.pop(field.name, None)
        return data

    def presentation(self) -> dict:
        """The presentation fields (outside the protocol and its hash): what the manifest's "presentation" records."""
        return {field.name: getattr(self, field.name) for field, o in options(type(self)) if not o.hashed}

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


def recorded_presentation(manifest: dict) -> dict:
    """The presentation a run was made with (OutputOptions.presentation()): the manifest's "presentation", else, in a
    run made when the colour map was part of the protocol, the protocol's own (`protocol.outputs.cmap`)."""
    if isinstance(manifest.get("presentation"), dict):
        return dict(manifest["presentation"])
    outputs = (manifest.get("protocol") or {}).get("outputs") or {}
    return {"cmap": outputs["cmap"]} if isinstance(outputs.get("cmap"), str) else {}


class EpisodeWriter:
    """Writes one episode's outputs from `StepRecord`s in a background thread (see the module docstring): a queue,
    the thread that finishes each step and hands it to the sinks, and the atomic finish (episode.json last).

    Use as a context manager, or call `finish(summary)` on success and `abort()` on failure.
    """

    def __init__(self, episode_dir: str | os.PathLike, tokens: TokenMap | None, meta: EpisodeMeta,
                 options: OutputOptions | None = None, viewer: str | None = None):
        """tokens: the token map of the attention; a record's own `StepRecord.tokens` (the map of the
        inference that produced it) takes precedence, so None is fine when the records carry one, or when they
        carry no attention (a policy without it).
        viewer: gRPC url of a live Rerun viewer to stream the episode to (harness.outputs.rerun_viewer.start_viewer)."""
        self.dir = Path(episode_dir)
        self.meta = meta
        self.options = options or OutputOptions()
        self.dir.mkdir(parents=True, exist_ok=True)
        (self.dir / "episode.json").unlink(missing_ok=True)  # the directory is incomplete until finish()

        self._queue: queue.Queue = queue.Queue(maxsize=self.options.queue_size)
        self._error: BaseException | None = None
        self._error_step: int | None = None
        self._aborting = threading.Event()
        self._done = False
        self._finisher = StepFinisher(tokens, self.options)  # StepRecord -> FinishedStep (background thread only)
        self._sinks = open_sinks(self.dir, meta, self.options, viewer)  # harness.outputs.sinks.sink_table(), in order
        # per step, for episode.json (background thread only, read after join): the record's timings and "write"
        self._timings: list[dict[str, float]] = []
        self._rewards: list[float] = []
        self._success: list[bool] = []
        self._blocked: list[float] = []  # caller side: seconds each add_step waited for queue space

        self._thread = threading.Thread(target=self._run, name=f"episode-writer-{meta.task}-{meta.episode}", daemon=True)
        self._thread.start()

    @property
    def tokens(self) -> TokenMap | None:
        """The episode's token map: the one given, or the first record's own."""
        return self._finisher.tokens

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
        """Wait for the queue, close every sink (video, arrays, metrics, recording) and finally write episode.json.
        Returns the summary written (with `episode_dir` and absolute `paths` added). `summary` entries override the
        computed ones (dict entries such as "timings" are merged key by key)."""
        if self._done:
            raise RuntimeError("this episode writer is already finished or aborted")
        start = time.perf_counter()
        try:
            self._put(_STOP)
            self._thread.join()
            self._raise_if_failed()
            end = EpisodeEnd(self.tokens, self._outcome(summary or {}), tuple(self._timings), tuple(self._blocked))
            files: dict = {}
            for sink in self._sinks:
                files.update(sink.close(end))
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
        for sink in self._sinks:
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
                for sink in self._sinks:  # deferred panels, encoders closing
                    sink.end()
        except BaseException as err:  # surfaced in the caller by add_step / finish
            self._error, self._error_step = err, step

    def _process(self, record: StepRecord) -> None:
        """One step: finished once, then handed to every sink in the table's order."""
        finished = self._finisher(record)
        for sink in self._sinks:
            sink.add(finished)
        self._rewards.append(float(record.reward))
        self._success.append(bool(record.success))
        self._timings.append({k: float(v) for k, v in record.timings.items()})

    # ---- at finish -----------------------------------------------------------------------------

    def _outcome(self, summary: dict) -> dict:
        """The episode's outcome as the recording shows it: success (the caller's when given), steps, return."""
        outcome = {"success": bool(summary.get("success", any(self._success))), "steps": len(self._rewards),
                   "return": float(np.sum(self._rewards)) if self._rewards else 0.0}
        for key in ("actions_clipped",):
            if key in summary:
                outcome[key] = summary[key]
        return outcome

    def _without_attention(self) -> bool:
        """The episode's steps carry no attention (its policy gives none), or it has no step and no token map."""
        layout = self._finisher.layout
        return not layout.attention if layout is not None else self.tokens is None

    def _summary(self, files: dict, summary: dict, finish_s: float) -> dict:
        n = len(self._rewards)
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
        }
        for sink in self._sinks:  # png_encode, rerun
            timings.update(sink.timings())
        layout = self._finisher.layout
        result = {
            **dataclasses.asdict(self.meta),
            "success": any(self._success),
            "steps": n,
            "return": float(np.sum(self._rewards)) if n else 0.0,
            "layers": layout.layers if layout and layout.attention else None,
            "heads": layout.heads if layout and layout.attention else None,
            "keys": self.tokens.num_keys if self.tokens is not None else None,
            **({"attention": False} if self._without_attention() else {}),
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

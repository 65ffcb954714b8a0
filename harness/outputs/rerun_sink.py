"""The Rerun viewer sink: one episode's finished step records as a Rerun recording (`episode.rrd`), or live.

Optional: it needs the `viewer` extra (`pip install 'octo-harness[viewer]'`, rerun-sdk 0.23.x), imported only
when a recording is asked for; without it `import_rerun` raises one line naming that command. A Rerun viewer reads
only recordings of its own minor version, so the version is pinned and checked.

`RerunSink(meta, options, save=PATH, connect=URL)` receives `StepRecord`s with their token map and metrics and logs
them with Rerun's own APIs: compressed images (JPEG, with the encoder `rr.Image(...).compress()` uses; the target mask
and the probes' layers as transparent PNGs), tensors, scalars (`rr.Scalars`, sent as columns with `rr.send_columns` at
the end of a saved episode), text documents, and a default blueprint (`rerun.blueprint`) that lays out the first view. `save`: the
recording goes to `<name>.tmp.<pid>.rrd` and is moved onto `PATH` by `finish()` (never half-written under its final
name; `abort()` deletes it). `connect`: streamed to a live viewer's gRPC address (harness.outputs.rerun_viewer: a
local native viewer, `spawn`, or a web viewer served for a headless machine, `serve`). Both at once log every step to
both. `RerunRecording` is the episode writer's sink around it (OutputOptions.rerun, or a live viewer's url); `view`
uses `RerunSink` directly to build a recording from a run's arrays. The timelines and entity tree are
harness.outputs.rerun_layout's.

Overlays use the same colours and interpolation as the PNGs and the MP4 (OutputOptions.overlay_interpolation).
"""

from __future__ import annotations

import io
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from envs.phases import phase_names
from harness.measures.attention import camera_maps, fuse_heads
from harness.files import temp_path
from harness.octo.tokens import TokenMap
from harness.outputs.overlays import heatmap_overlays, resize_nearest
from harness import probes
from harness.outputs.rerun_layout import LAYER_DRAW_ORDER, blueprint, entity, mask_png, overlay_base
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink
from harness.records import EpisodeMeta, StepRecord

RERUN_MINOR = "0.23"  # recordings are readable by viewers of this minor version only
INSTALL = "pip install 'octo-harness[viewer]'"
RRD_NAME = "episode.rrd"
APPLICATION_ID = "octo-harness"
MODES = ("save", "spawn", "serve")
JPEG_QUALITY = 90
TENSOR_DIMS = ["layer", "head", "row", "col"]
TARGET_DRAW_ORDER = 5.0  # the target mask is drawn above the frame (images default to -10)
DRAW_ORDER = {"png": TARGET_DRAW_ORDER, "layer": LAYER_DRAW_ORDER}  # PNG layers over a frame: target mask, a probe's layer


class ViewerUnavailableError(ValueError):
    """The Rerun SDK is missing or of another minor version (one line naming the install command)."""


def import_rerun():
    """The `rerun` module, checked: installed, and of the minor version recordings are written for."""
    try:
        import rerun as rr
    except ImportError:
        raise ViewerUnavailableError(f"the Rerun viewer is an optional extra and is not installed; install it with {INSTALL}") from None
    version = str(getattr(rr, "__version__", "unknown"))
    if not version.startswith(RERUN_MINOR + "."):
        raise ViewerUnavailableError(f"rerun-sdk {version} is installed, but octo-harness writes recordings for Rerun "
                                     f"{RERUN_MINOR}.x (a viewer reads only its own minor version); {INSTALL}")
    return rr


def parse_modes(text: str | None) -> tuple[str, ...]:
    """--rerun MODE[,MODE]: save, spawn, serve (spawn and serve exclude each other) -> sorted tuple ('' -> ())."""
    if text is None:
        return ()
    modes = tuple(dict.fromkeys(m.strip() for m in str(text).split(",") if m.strip()))
    unknown = [m for m in modes if m not in MODES]
    if unknown or not modes:
        raise ValueError(f"--rerun takes save, spawn or serve (or save,spawn / save,serve); got {text!r}")
    if "spawn" in modes and "serve" in modes:
        raise ValueError("--rerun spawn (a viewer on this machine) and serve (a web viewer for a remote browser) "
                         "exclude each other; choose one")
    return modes


def recording_id(meta: EpisodeMeta) -> str:
    return f"{meta.run}/{meta.task}/episode_{meta.episode}"


# ---------------------------------------------------------------------------------------------- the sink

@dataclass(frozen=True)
class SinkOptions:
    """What the sink draws, from OutputOptions (the PNGs' and MP4's colours and interpolation)."""

    cmap: str = "viridis"
    alpha: float = 0.5
    head_fusion: str = "mean"
    interpolation: str = "nearest"
    jpeg_quality: int = JPEG_QUALITY


class RerunSink:
    """Logs one episode's step records into a Rerun recording (see the module docstring).

    save: path of the .rrd to write (atomically, at `finish`); connect: gRPC url of a live viewer. Call `log_step`
    per step (in order), then `finish(outcome)` or `abort()`. Arrays: frames (H, W, 3) uint8; attention
    (layers, heads, readouts, keys).

    A live viewer gets every entity as it is logged (`rr.log`); the saved recording buffers each entity's images and
    scalars and sends them as columns (`rr.send_columns`, one call per entity every FLUSH_STEPS steps and at the end),
    which costs a fraction of one `log` call per entity and step (tensors are logged per step: Rerun 0.23 takes no
    column of tensors).
    """

    FLUSH_STEPS = 64  # buffered steps per column batch of the saved recording (bounds the memory it holds)

    def __init__(self, meta: EpisodeMeta, options: SinkOptions | None = None, *, save: str | os.PathLike | None = None,
                 connect: str | None = None, intervention: bool = False, control_hz: float | None = None):
        if save is None and connect is None:
            raise ValueError("a RerunSink needs a file to save to or a viewer to connect to")
        rr = import_rerun()
        self.rr = rr
        self.meta = meta
        self.options = options or SinkOptions()
        self.path = Path(save) if save is not None else None
        self.temp = temp_path(self.path) if self.path is not None else None
        self.intervention = intervention
        self.control_hz = control_hz
        self.file = self.live = None
        self._binary = self._out = None
        if self.path is not None:
            # the encoded bytes are written here, not by Rerun's file sink: that one only logs a failed write (a full
            # disk) and leaves a cut recording behind; here the OSError reaches the caller and the temp file goes
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._out = open(self.temp, "wb")
            self.file = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(meta))
            self._binary = self.file.binary_stream()
        if connect is not None:
            self.live = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(meta))
            self.live.connect_grpc(connect)
        self._started = False
        self._buffer: dict[str, tuple[str, list[int], list]] = {}  # entity -> (kind, steps, values) for the file
        self._buffered_steps = 0
        self._targets: dict[str, np.ndarray] = {}  # camera -> the target mask logged last
        self._steps: list[int] = []
        self._done = False

    @property
    def streams(self) -> list:
        return [s for s in (self.file, self.live) if s is not None]

    # ---- logging helpers ---------------------------------------------------------------------

    def _static(self, path: str, *archetypes) -> None:
        for stream in self.streams:
            stream.log(path, *archetypes, static=True)

    def _emit(self, path: str, kind: str, value) -> None:
        """One entity's value at the current step: logged live at once, buffered as a column for the file.
        kind: "jpeg", "png" (the target mask) / "layer" (a probe's layer): encoded bytes; "tensor" ((array, dim
        names)), "scalars" ((n,) float64)."""
        if self.live is not None:
            rr = self.rr
            if kind in ("jpeg", "png", "layer"):
                archetype = rr.EncodedImage(contents=value, media_type="image/jpeg" if kind == "jpeg" else "image/png",
                                            draw_order=DRAW_ORDER.get(kind))
            elif kind == "tensor":
                archetype = rr.Tensor(value[0], dim_names=value[1])
            else:
                archetype = rr.Scalars(value)
            self.live.log(path, archetype)
        if self.file is not None and kind == "tensor":  # Rerun 0.23 sends no batch of tensors as a column: log it now
            self.file.set_time("step", sequence=self._steps[-1])
            if self.control_hz:
                self.file.set_time("sim_time", duration=self._steps[-1] / self.control_hz)
            self.file.log(path, self.rr.Tensor(value[0], dim_names=value[1]))
        elif self.file is not None:
            self._buffer.setdefault(path, (kind, [], []))
            self._buffer[path][1].append(self._steps[-1])
            self._buffer[path][2].append(value)

    @staticmethod
    def _layers(record: StepRecord) -> list[tuple[Any, Any]]:
        """(viewer layer, payload) of every registered probe with a layer whose payload this step carries."""
        return [(layer, record.probes[cls.name]) for cls, layer in probes.parts("layer") if cls.name in record.probes]

    def image(self, path: str, image: np.ndarray) -> None:
        """Log an (H, W, 3) uint8 image at `path` for this step (JPEG; a probe's layer draws with it)."""
        self._image(path, image)

    def layer(self, path: str, png: bytes) -> None:
        """Log a transparent RGBA PNG over a frame at `path` for this step (drawn above it, below the target mask)."""
        self._emit(path, "layer", png)

    def scalars(self, path: str, values, names: list[str] | None = None) -> None:
        """Log one or more scalars at `path` for this step (a series on the timeline)."""
        self._scalars(path, values, names)

    def _image(self, path: str, image: np.ndarray) -> None:
        """JPEG of an (H, W, 3) uint8 image: Pillow's encoder at the quality rr.Image.compress uses it with."""
        out = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(image)).save(out, format="JPEG", quality=self.options.jpeg_quality)
        self._emit(path, "jpeg", out.getvalue())

    def _scalars(self, path: str, values, names: list[str] | None = None) -> None:
        values = np.atleast_1d(np.asarray(values, np.float64))
        if path not in self._buffer and path not in self._styled:
            self._styled.add(path)
            rr = self.rr
            style = (rr.SeriesPoints(markers="diamond", marker_sizes=6.0, names=names or ["new action chunk"])
                     if path == "scalars/new_chunk" else rr.SeriesLines(names=names) if names else None)
            if style is not None:
                self._static(path, style)
        self._emit(path, "scalars", values)

    _styled: set

    def _flush_columns(self) -> None:
        """The buffered values of the saved recording, one send_columns call per entity."""
        rr = self.rr
        for path, (kind, steps, values) in self._buffer.items():
            if not steps:
                continue
            index = np.asarray(steps, np.int64)
            indexes = [rr.TimeColumn("step", sequence=index)]
            if self.control_hz:
                indexes.append(rr.TimeColumn("sim_time", duration=index / self.control_hz))
            if kind in ("jpeg", "png", "layer"):
                columns = rr.EncodedImage.columns(blob=values, media_type=["image/jpeg" if kind == "jpeg" else "image/png"]
                                                  * len(values), **({"draw_order": [DRAW_ORDER[kind]] * len(values)}
                                                                    if kind in DRAW_ORDER else {}))
            else:
                columns = rr.Scalars.columns(scalars=np.stack(values))
            self.file.send_columns(path, indexes=indexes, columns=columns)
            steps.clear()
            values.clear()
        self._buffered_steps = 0

    # ---- steps ---------------------------------------------------------------------------------

    def _start(self, record: StepRecord, layers: int, cameras: list[str]) -> None:
        rr = self.rr
        self._styled = set()
        shown = self._layers(record)  # the probes' layers of step 0 (a step of every probe's period) set the views
        attention = record.readout_attention is not None
        bp = blueprint(cameras, layers, self.intervention, shown) if attention else \
            blueprint(cameras, 0, self.intervention, shown, attention=False)
        for stream in self.streams:
            stream.send_blueprint(bp, make_active=True, make_default=True)
        meta = self.meta
        header = [f"# {meta.task}, episode {meta.episode} (seed {meta.seed})", "", f"**Instruction:** {meta.instruction}",
                  "", f"- run: {meta.run}", f"- model: {meta.model}" + (" (**RANDOM WEIGHTS**)" if meta.model_is_random else ""),
                  f"- execution: {meta.execution}", f"- text tokenizer: {meta.text_tokenizer}"]
        if self.intervention:
            header.append(f"- intervention: {meta.extra.get('intervention')}")
        header.append("- green over the frames: the target object's mask")
        if not attention:
            header.append("- no attention: the policy gives none (frames, actions and scalars only)")
        for layer, payload in shown:
            header.extend(layer.header(payload))
        if meta.extra.get("frames_note"):
            header.append(f"- frames: {meta.extra['frames_note']}")
        self._static("episode/instruction", rr.TextDocument("\n".join(header), media_type="text/markdown"))
        self._static("episode/outcome", rr.TextDocument("(episode running)"))

    def log_step(self, record: StepRecord, tokens: TokenMap | None, metrics: dict[str, np.ndarray] | None = None) -> None:
        """One control step. tokens: the token map of its attention; metrics: attention.step_metrics of it (as
        metrics.jsonl / attention.npz hold them; the measures plotted), None to skip the measures. A step without
        attention (its readout_attention None: a policy that gives none) logs its frames, masks, actions and
        scalars, no attention entities (tokens may be None)."""
        if self._done:
            raise RuntimeError("this recording is finished")
        opts = self.options
        attn = None
        if record.readout_attention is not None:
            attn = np.asarray(record.readout_attention, np.float16).astype(np.float32)  # as attention.npz stores it
            if attn.ndim != 4 or attn.shape[-1] != tokens.num_keys:
                raise ValueError(f"readout_attention must be (layers, heads, readouts, keys={tokens.num_keys}); "
                                 f"got {attn.shape}")
        layers = attn.shape[0] if attn is not None else 0
        # maps of every camera; frames where the record has them (without attention: the record's frames)
        cameras = [key for _, key, _, _ in tokens.image_groups] if attn is not None else list(record.frames)
        if not self._started:
            self._start(record, layers, cameras)
            self._started = True
        step = int(record.step)
        self._steps.append(step)
        if self.live is not None:
            self.live.set_time("step", sequence=step)
            if self.control_hz:
                self.live.set_time("sim_time", duration=step / self.control_hz)

        for cam in cameras:
            if attn is not None:
                heads = camera_maps(attn, tokens, cam).mean(axis=2)  # (layers, heads, rows, cols)
                self._emit(entity("attention", cam, "heads"), "tensor", (heads, TENSOR_DIMS))
            if cam not in record.frames:
                continue
            frame = np.asarray(record.frames[cam])
            self._image(entity("camera", cam), frame)
            target = ((record.masks or {}).get(cam) or {}).get("target")
            if target is not None:
                target = resize_nearest(np.asarray(target, bool), *frame.shape[:2])
                previous = self._targets.get(cam)
                if previous is None or not np.array_equal(previous, target):  # logged when it changes (latest-at holds it)
                    self._targets[cam] = target
                    self._emit(entity("camera", cam, "target"), "png", mask_png(target))
            if attn is not None:
                fused = fuse_heads(heads, opts.head_fusion, axis=1)  # (layers, rows, cols)
                shown = overlay_base(frame)
                overlays = heatmap_overlays(shown, fused, alpha=opts.alpha, cmap=opts.cmap,
                                            interpolation=opts.interpolation)
                for layer in range(layers):
                    self._image(entity("attention", cam, f"layer_{layer:02d}"), overlays[layer])
            seen = (record.policy_inputs or {}).get(cam)
            if self.intervention and seen is not None and np.ndim(seen) == 3:
                self._image(entity("intervention", cam), np.asarray(seen, np.uint8))

        executed = np.asarray(record.action_executed, np.float64).ravel()
        chunk = np.asarray(record.actions_predicted, np.float32)
        dims = [f"a{i}" for i in range(executed.size)]
        self._scalars("actions/executed", executed, [f"executed {d}" for d in dims])
        if chunk.ndim == 2 and chunk.shape[0]:
            self._scalars("actions/predicted", chunk[0], [f"predicted {d}" for d in dims[:chunk.shape[1]]])
            self._emit("actions/chunk", "tensor", (chunk, ["horizon", "action"]))
        self._scalars("scalars/reward", float(record.reward), ["reward"])
        self._scalars("scalars/success", float(bool(record.success)), ["success"])
        if record.inferred:
            self._scalars("scalars/new_chunk", 1.0)
        phases = phase_names(self.meta.task) if getattr(record, "phase", None) is not None else ()
        if record.phase in phases:  # the task phase on the timeline, as its index (envs.phases)
            self._scalars("scalars/phase", float(phases.index(record.phase)),
                          ["phase: " + ", ".join(f"{i} {name}" for i, name in enumerate(phases))])
        for layer, payload in self._layers(record):  # the per-step probes' layers, at the steps that carry them
            layer.log(self, record, payload)
        for name, values in (metrics or {}).items():
            self._measure(name, np.asarray(values, np.float32), metrics)
        self._buffered_steps += 1
        if self.file is not None and self._buffered_steps >= self.FLUSH_STEPS:
            self._flush_columns()
            self._drain()

    def _drain(self) -> None:
        """Write what the file stream has encoded so far (an OSError, e.g. a full disk, propagates)."""
        data = self._binary.read(flush=True) if self._binary is not None else None
        if data:
            self._out.write(data)

    def _measure(self, name: str, values: np.ndarray, metrics: dict) -> None:
        if name.startswith("mask_area/") or values.ndim != 1:
            return  # the chance level is folded into the lift
        names = [f"layer {i}" for i in range(values.size)]
        self._scalars(entity("measures", *name.split("/")), values, names)
        if name.startswith("mask_mass/"):
            area = metrics.get("mask_area/" + name[len("mask_mass/"):])
            if area is not None and float(np.asarray(area)) > 0:
                lift = values.astype(np.float64) / float(np.asarray(area, np.float32))
                self._scalars(entity("measures", "mask_lift", *name.split("/")[1:]), lift, names)

    # ---- end -------------------------------------------------------------------------------------

    def finish(self, outcome: dict | None = None) -> Path | None:
        """Send the buffered columns and the outcome, close the recording and move the file into place."""
        if self._done:
            raise RuntimeError("this recording is already finished or aborted")
        self._done = True
        try:
            if self.file is not None:
                self._flush_columns()
            outcome = outcome or {}
            lines = [f"# {'SUCCESS' if outcome.get('success') else 'no success'}", ""]
            lines += [f"- {key}: {value}" for key, value in outcome.items() if key != "success"]
            self._static("episode/outcome", self.rr.TextDocument("\n".join(lines), media_type="text/markdown"))
            for stream in self.streams:
                stream.flush(blocking=True)
            self._drain()
            for stream in self.streams:
                stream.disconnect()
            self._drain()
            self.file = self.live = None
            if self.path is not None:
                out, self._out, self._binary = self._out, None, None
                out.flush()
                os.fsync(out.fileno())
                out.close()
                os.replace(self.temp, self.path)
        except BaseException:
            self._discard()
            raise
        return self.path

    def abort(self) -> None:
        """Stop logging and delete the temporary file; nothing is written under the final name."""
        if self._done:
            return
        self._done = True
        self._discard()

    def _discard(self) -> None:
        for stream in self.streams:
            try:
                stream.disconnect()
            except Exception:  # noqa: BLE001 - already gone; the file is removed below either way
                pass
        self.file = self.live = None
        self._buffer = {}
        self._binary = None
        if self._out is not None:
            out, self._out = self._out, None
            try:
                out.close()
            except OSError:  # the close's own flush failed (a full disk): the file is deleted below anyway
                pass
        if self.temp is not None:
            self.temp.unlink(missing_ok=True)


class RerunRecording(Sink):
    """The episode writer's Rerun sink: episode.rrd with OutputOptions.rerun, and/or a live viewer's gRPC url
    (`viewer`). A stale episode.rrd is removed when it starts; its outcome is the writer's (`EpisodeEnd.outcome`)."""

    @classmethod
    def wanted(cls, options, viewer) -> bool:
        return options.rerun or viewer is not None

    def __init__(self, directory, meta: EpisodeMeta, options, viewer: str | None = None):
        super().__init__(directory, meta, options, viewer)
        (self.dir / RRD_NAME).unlink(missing_ok=True)  # never a stale recording beside a new episode
        self.sink = RerunSink(
            meta, SinkOptions(cmap=options.cmap, alpha=options.alpha, head_fusion=options.head_fusion,
                              interpolation=options.overlay_interpolation),
            save=self.dir / RRD_NAME if options.rerun else None, connect=viewer,
            intervention=bool(meta.extra.get("intervention")), control_hz=meta.extra.get("control_hz"))
        self.seconds = 0.0  # logging the recording (in the writer thread) and closing it

    def add(self, step: FinishedStep) -> None:
        start = time.perf_counter()
        self.sink.log_step(step.record, step.tokens, step.metrics)
        self.seconds += time.perf_counter() - start

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        start = time.perf_counter()
        path = self.sink.finish(end.outcome)
        self.seconds += time.perf_counter() - start
        return {"rerun": path.name} if path is not None else {}

    def abort(self) -> None:
        self.sink.abort()

    def timings(self) -> dict[str, Any]:
        return {"rerun": self.seconds}

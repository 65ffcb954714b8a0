"""What every output sink receives: the finished step, built once per step, and the interface a sink implements.

The episode writer's background thread turns each `StepRecord` of the control loop into a `FinishedStep` with
`StepFinisher` (checks, attention metrics, per-camera maps, target boxes, the rollout row) and hands it to every sink
of `harness.outputs.sinks.sink_table()` in order. A sink (`Sink`) keeps what its files need from each step and writes them
when the episode closes. Arrays in a `FinishedStep`:

  attention        (layers, heads, readouts, keys) float32: the step's readout attention
  metrics          name -> per-layer values (attention.step_metrics: shares, entropy, mask mass and area)
  frames           camera -> (height, width, 3) uint8: the frames the model saw, of the layout's cameras
  maps             camera -> (layers, heads, rows, cols) float32: readout attention on its patch grid, readouts averaged
  boxes            camera -> (y0, x0, y1, x1) the target mask's box in frame pixels (OutputOptions.bbox; None: no mask)
  rollout          (readouts, keys) float32: attention rollout rows, with video_attention="rollout" (else None)

A step of a policy without attention (`StepRecord.readout_attention` None: harness.policies.Capabilities) has no token
map: its `attention` and `tokens` are None, `metrics`, `maps` and `boxes`' attention parts empty, and its layout has
`attention` False, no layers and the cameras of its frames; the sinks write everything else and skip attention.
An episode's steps either all carry attention or none does (a ValueError names the first that differs).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from harness.measures.attention import camera_maps, rollout_readout_rows, step_metrics
from harness.octo.tokens import TokenMap
from harness.outputs.overlays import mask_bbox
from harness.records import EpisodeMeta, StepRecord

# `options` below are harness.outputs.writers.OutputOptions (annotated by name: the writer imports the sinks, so they
# cannot import it back)
OutputOptions = Any


@dataclass(frozen=True)
class Layout:
    """What the first step fixes for the whole episode."""

    layers: int
    heads: int
    png_layers: tuple[int, ...]
    cameras: tuple[str, ...]  # observation keys with an image group and a frame
    video_cameras: tuple[str, ...]  # the video's rows
    video_layer: int | None  # the layer the video shows; None when it shows the rollout or an attribution map
    attention: bool = True  # False: the policy gives no attention (no layers, no maps; cameras: the frames' keys)


@dataclass(frozen=True, eq=False)
class FinishedStep:
    """One control step as the sinks receive it (arrays: see the module docstring)."""

    record: StepRecord  # as the control loop handed it over
    tokens: TokenMap | None  # what each key of `attention` is (None: the policy gives no attention)
    layout: Layout
    attention: np.ndarray | None  # None: the policy gives no attention
    metrics: dict[str, np.ndarray]
    frames: dict[str, np.ndarray]
    maps: dict[str, np.ndarray]
    boxes: dict[str, tuple[int, int, int, int] | None]
    rollout: np.ndarray | None = None

    @property
    def step(self) -> int:
        return int(self.record.step)


@dataclass(frozen=True)
class EpisodeEnd:
    """What the writer knows when the episode closes, handed to every sink's `close`."""

    tokens: TokenMap | None  # the episode's token map (the writer's own when no step carried one)
    outcome: dict  # success, steps, return and actions_clipped (when the caller gave it): the recording's outcome
    timings: tuple[dict[str, float], ...]  # per step: the record's timings (seconds) and the writer's "write"
    blocked: tuple[float, ...]  # seconds each add_step waited for queue space


class Sink:
    """One output of an episode. The writer makes every sink of the table whose `wanted(options, viewer)` is true
    with `(directory, meta, options, viewer)`, calls `add(step)` per step and `end()` after the last one in its
    background thread, then `close(end)` in `finish()` (which writes the files and returns the entries for
    episode.json's `files`), or `abort()` on failure (delete temporaries; the writer removes `*.tmp.*` after)."""

    def __init__(self, directory: Path, meta: EpisodeMeta, options: OutputOptions, viewer: str | None = None):
        self.dir = Path(directory)
        self.meta = meta
        self.options = options

    @classmethod
    def wanted(cls, options: OutputOptions, viewer: str | None) -> bool:
        return True

    def add(self, step: FinishedStep) -> None:
        raise NotImplementedError

    def end(self) -> None:
        """After the last step, in the writer's thread (encoders finish here)."""

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        """Write the files; their entries of episode.json's `files` (name -> file name, or a count / pattern)."""
        return {}

    def abort(self) -> None:
        """Stop and delete what this sink has half-written."""

    def timings(self) -> dict[str, Any]:
        """Entries of episode.json's `timings` (seconds this sink spent)."""
        return {}


def scaled_box(mask: np.ndarray | None, frame: np.ndarray) -> tuple[int, int, int, int] | None:
    """Bounding box of a mask, in the pixels of `frame` (the mask may be at camera resolution)."""
    box = mask_bbox(mask)
    if box is None:
        return None
    sy = frame.shape[0] / mask.shape[0]
    sx = frame.shape[1] / mask.shape[1]
    y0, x0, y1, x1 = box
    return int(y0 * sy), int(x0 * sx), max(int(y0 * sy) + 1, round(y1 * sy)), max(int(x0 * sx) + 1, round(x1 * sx))


def resolve_layout(record: StepRecord, attn: np.ndarray, tokens: TokenMap, opts: OutputOptions) -> Layout:
    """The episode's layout from its first step; a layer or camera the options name that the model lacks is a
    ValueError naming the choices."""
    layers, heads = attn.shape[:2]

    def layer_index(i: int) -> int:
        if not -layers <= i < layers:
            raise ValueError(f"layer {i} is out of range for a model with {layers} layers; choose 0..{layers - 1}")
        return i % layers

    png_layers = tuple(range(layers)) if opts.layers is None else tuple(sorted({layer_index(i) for i in opts.layers}))
    cameras = tuple(key for _, key, _, _ in tokens.image_groups if key in record.frames)
    if not cameras and (opts.png_every or opts.video or opts.gif):
        raise ValueError(f"no frame for any camera of the model {[k for _, k, _, _ in tokens.image_groups]}; "
                         "put the frames the model saw in StepRecord.frames")
    video_cameras = opts.video_cameras or cameras
    unknown = [c for c in video_cameras if c not in cameras]
    if (opts.video or opts.gif) and unknown:
        raise ValueError(f"video camera(s) {unknown} have no frame or image group; choose from {list(cameras)}")
    # OutputOptions checked video_attention: a layer index, "rollout" or an attribution method
    video_layer = layer_index(opts.video_attention) if isinstance(opts.video_attention, int) else None
    return Layout(layers, heads, png_layers, cameras, tuple(video_cameras), video_layer)


class StepFinisher:
    """StepRecord -> FinishedStep, checking each step against the episode's token map and layout (a ValueError names
    what differs). tokens: the episode's token map; a record's own `StepRecord.tokens` takes precedence."""

    def __init__(self, tokens: TokenMap | None, options: OutputOptions):
        self.tokens = tokens
        self.options = options
        self.layout: Layout | None = None

    def __call__(self, record: StepRecord) -> FinishedStep:
        if self.layout is not None and (record.readout_attention is not None) != self.layout.attention:
            raise ValueError(f"step {record.step}: {'no ' if record.readout_attention is None else ''}readout attention, "
                             f"but the episode started {'with' if self.layout.attention else 'without'} it")
        if record.readout_attention is None:
            return self._without_attention(record)
        if record.tokens is not None:
            if self.layout is None:
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
        if self.layout is None:
            self.layout = resolve_layout(record, attn, tokens, opts)
        layout = self.layout
        if attn.shape[:2] != (layout.layers, layout.heads):
            raise ValueError(f"step {record.step}: attention has shape {attn.shape}, the episode started with "
                             f"{layout.layers} layers and {layout.heads} heads")
        metrics = step_metrics(attn, tokens, record.masks)
        frames = {cam: record.frames[cam] for cam in layout.cameras}
        maps = {cam: camera_maps(attn, tokens, cam).mean(axis=2) for cam in layout.cameras}
        boxes = {}
        if opts.bbox and record.masks:
            for cam in layout.cameras:
                target = (record.masks.get(cam) or {}).get("target")
                if target is not None:
                    boxes[cam] = scaled_box(np.asarray(target, bool), frames[cam])
        rollout = None
        if opts.video_attention == "rollout":
            if record.full_attention is None:
                raise ValueError("video_attention='rollout' needs full attention matrices; "
                                 "request full attention from the policy or choose a layer index")
            rollout = rollout_readout_rows(record.full_attention, tokens, head_fusion=opts.head_fusion)  # (readouts, keys)
        return FinishedStep(record, tokens, layout, attn, metrics, frames, maps, boxes, rollout)

    def _without_attention(self, record: StepRecord) -> FinishedStep:
        """A step of a policy without attention: its frames, target boxes and the record, no maps or metrics."""
        opts = self.options
        if self.layout is None:
            cameras = tuple(record.frames)
            video_cameras = opts.video_cameras or cameras
            unknown = [c for c in video_cameras if c not in cameras]
            if (opts.video or opts.gif) and unknown:
                raise ValueError(f"video camera(s) {unknown} have no frame; choose from {list(cameras)}")
            self.layout = Layout(0, 0, (), cameras, tuple(video_cameras), None, attention=False)
        frames = {cam: record.frames[cam] for cam in self.layout.cameras if cam in record.frames}
        boxes = {}
        if opts.bbox and record.masks:
            for cam in frames:
                target = (record.masks.get(cam) or {}).get("target")
                if target is not None:
                    boxes[cam] = scaled_box(np.asarray(target, bool), frames[cam])
        return FinishedStep(record, None, self.layout, None, {}, frames, {}, boxes)


def phase_names_of(task: str, phases: list[str | None]) -> tuple[str, ...]:
    """The task's phases when any step recorded one (else ()); a phase the task lacks is a ValueError."""
    if not any(p is not None for p in phases):
        return ()
    from envs.phases import phase_names

    names = phase_names(task)
    unknown = sorted({p for p in phases if p is not None and p not in names})
    if unknown:
        raise ValueError(f"phases {unknown} are not phases of task {task} ({', '.join(names) or 'none'})")
    return names

"""What a run's files take on disk, before it runs; and a disk that fills while it runs.

Before the first episode (after the checkpoint loads: its layers, heads and tokens size the arrays; before any env
is made or anything compiles) the driver estimates what the episodes left to run will write (`estimate`): every
episode up to its step limit, PNG panels, MP4, arrays and lines per step, from the protocol and the model's shape.
When that exceeds the free space where the run writes (`free_bytes`), the run is refused: one line naming the
cheaper flags (`NotEnoughSpace`, exit 2). `--no-space-check` runs anyway.

During the run, a write the disk refuses (ENOSPC, EDQUOT; `disk_error`) ends the episode as an infrastructure
failure whose lost part is "disk" (harness.run.executor.failure_of): its folder is removed, it is never retried,
the driver records its row and stops the run at once (`DiskFullError`: one line naming the folder and the space the
episodes left need, exit 2). Its job, and those in flight on other workers, stay to do: a plain resume runs them.

The byte rates below were measured on the reference policy (models/octo-reference-robosuite, Lift, defaults) and
the tiny fixture (benchmarks/bench_run_cost.py prints estimate and measured size side by side); episodes that
succeed end before their step limit, so a run usually writes less than its estimate.
"""

from __future__ import annotations

import errno
import math
import os
import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from harness.options import option

DISK = "disk"  # the lost part of an episode whose disk filled (EpisodeRow.lost)
DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
_DISK_TEXTS = tuple(os.strerror(e) for e in DISK_ERRNOS)  # ffmpeg reports its own failed write as text only

PNG_BYTES_PER_PIXEL = 0.6  # a layer panel (zlib level 2), per pixel of its camera cells
MP4_BYTES_PER_PIXEL = 0.18  # rollout.mp4 (x264 crf 20), per camera pixel and frame
GIF_BYTES_PER_PIXEL = 0.4  # rollout.gif, per camera pixel of each kept frame
INPUT_BYTES_PER_PIXEL = 1.5  # inputs.npz (compressed RGB at the model's sizes)
NPZ_ARRAY_BYTES = 320  # an array's zip and .npy headers in an .npz
JSON_NUMBER_BYTES = 12  # a number in metrics.jsonl, with its separator
MASKS = 5  # mask labels per camera (target, robot, gripper, arm, background)
MIN_CELL = 128  # layer panels enlarge a frame by an integer factor to at least this height (overlays.layer_panel)
EPISODE_BYTES = 8_000  # episode.json, its row in results.jsonl, results.json and summary.csv
RUN_BYTES = 64_000  # manifest.json and the other run files


class NotEnoughSpace(ValueError):
    """The run's estimate exceeds the free space where it writes (one line, exit 2, before any episode)."""


class DiskFullError(RuntimeError):
    """A write the disk refused stopped the run (one line naming the folder and the space needed, exit 2)."""


@dataclass(frozen=True)
class SpaceCheck:
    """Whether a run compares the estimate of its files with the free space before it starts (changes no file)."""

    space_check: bool = option(True, "--no-space-check", "start even when the estimate of the run's files (every episode "
                         "up to its step limit) exceeds the free space where it writes", file=(bool,),
                         action="store_true", negated=True, hashed=False,
                         doc="start even when the estimate of the run's files (every episode up to its step limit) "
                             "exceeds the free space where it writes ([what a run costs](#what-a-run-costs))")


def disk_error(exc: BaseException | None) -> BaseException | None:
    """The exception in `exc`'s chain (cause, context) that says the disk is full or over quota, else None."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in DISK_ERRNOS:
            return exc
        if any(text in str(exc) for text in _DISK_TEXTS):
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def free_bytes(path: str | os.PathLike) -> int:
    """Free bytes (for this user) on the filesystem of `path`, or of its nearest existing parent."""
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free


def size_text(n: float) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if abs(n) >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n:.0f} B"


@dataclass(frozen=True)
class ModelShape:
    """What sizes a run's arrays: layers, heads, attention keys and readouts, patch grids and input sizes per camera."""

    layers: int
    heads: int
    keys: int
    readouts: int
    grids: dict  # observation key -> (rows, cols) of its patch grid
    image_sizes: dict  # observation key -> (height, width) the model reads
    horizon: int = 4

    @classmethod
    def of(cls, model) -> "ModelShape":
        tokens = model.token_map()
        shape = model.attention_shape
        if tokens is None or shape is None:  # a policy without attention writes no attention arrays or panels
            return cls(layers=0, heads=0, keys=0, readouts=0, grids={},
                       image_sizes={k: tuple(v) for k, v in model.image_sizes.items()},
                       horizon=int(getattr(model, "action_horizon", 4)))
        return cls(layers=shape.layers, heads=shape.heads,
                   keys=int(tokens.num_keys), readouts=len(tokens.readout_index),
                   grids={key: (int(r), int(c)) for _, key, r, c in tokens.image_groups},
                   image_sizes={k: tuple(v) for k, v in model.image_sizes.items()},
                   horizon=int(getattr(model, "action_horizon", 4)))


def task_cameras(protocol, task: str, shape: ModelShape) -> dict[str, int]:
    """{observation key: square frame size} of the cameras of `task` the model reads (the frames the outputs show)."""
    cameras = protocol.env_for(task).cameras
    if cameras is None:
        from envs import get_task, parse_cameras

        cameras = [(c.key, c.camera, c.size) for c in parse_cameras(None, get_task(task))]  # its suite's defaults
    read = {key: size for key, _, size in cameras if key in shape.image_sizes}
    return read or {key: size for key, _, size in cameras}


def task_steps(protocol, task: str) -> int:
    """The most steps an episode of `task` runs: --max-steps, else the task's limit."""
    if protocol.max_steps is not None:
        return int(protocol.max_steps)
    from envs import get_task

    return int(get_task(task).max_episode_steps)


def episode_bytes(protocol, task: str, shape: ModelShape, steps: int) -> dict[str, float]:
    """Bytes one episode of `task` that runs `steps` steps writes, by kind: png, video, arrays (npz, jsonl, json)."""
    out, policy, masks = protocol.outputs, protocol.policy, protocol.env_for(task).masks
    cams = task_cameras(protocol, task, shape)
    shown = {k: s * math.ceil(MIN_CELL / s) for k, s in cams.items()}  # as layer panels enlarge them
    png_steps = (steps - 1) // out.png_every + 1 if out.png_every and steps else 0
    png_layers = len(out.layers) if out.layers else shape.layers
    panel = (shape.heads + 1) * max(shown.values()) * sum(shown.values())
    sizes = {"png": png_steps * png_layers * panel * PNG_BYTES_PER_PIXEL, "video": 0.0}
    methods = len(policy.attribution.split(",")) + 1 if policy.attribution else 0  # the random control is added
    sizes["png"] += png_steps * methods * max(shown.values()) * sum(shown.values()) * PNG_BYTES_PER_PIXEL
    video_cams = [cams[k] for k in (out.video_cameras or cams) if k in cams] or list(cams.values())
    pixels = sum(s * s for s in video_cams)
    if out.video:
        sizes["video"] += steps * pixels * MP4_BYTES_PER_PIXEL + 20_000
    if out.gif:
        sizes["video"] += steps / out.gif_every * pixels * GIF_BYTES_PER_PIXEL
    sizes["arrays"] = _array_bytes(protocol, shape, len(cams), masks, steps) + EPISODE_BYTES
    return sizes


def _array_bytes(protocol, shape: ModelShape, cameras: int, masks: bool, steps: int) -> float:
    """attention.npz, actions.npz, metrics.jsonl and the optional arrays of one episode."""
    policy, out = protocol.policy, protocol.outputs
    attention = shape.layers * shape.heads * shape.readouts * shape.keys * 2  # float16 readout rows per step
    measures = (cameras + 3) + 3 + (2 * MASKS * cameras if masks else 0)  # shares, timestep shares, mask mass and lift
    cells = sum(r * c for r, c in shape.grids.values())
    per_step = (attention + (shape.layers * shape.heads + shape.layers) * 4 * measures
                + (MASKS * cells * 4 if masks else 0) + shape.horizon * 8 * 4 + 64
                + JSON_NUMBER_BYTES * (shape.layers * measures + MASKS * cameras + 12) + 300)  # metrics.jsonl row
    if policy.full_attention:
        per_step += shape.readouts * shape.keys * 2
    if out.record_inputs:
        per_step += sum(h * w * 3 for h, w in shape.image_sizes.values()) / 3 * INPUT_BYTES_PER_PIXEL
    if policy.attention_controls:
        every = policy.controls_every or 1
        per_step += len(policy.attention_controls.split(",")) * attention / every
    if policy.attribution:
        per_step += (len(policy.attribution.split(",")) + 1) * cells * 4
    headers = NPZ_ARRAY_BYTES * (2 * measures + 12 + 2 * MASKS * cameras + 20) + shape.keys * 140
    return headers + steps * per_step


@dataclass(frozen=True)
class Estimate:
    """The bytes the jobs of a run write, by kind, with every episode up to its step limit."""

    png: float
    video: float
    arrays: float
    episodes: int
    steps: tuple[int, ...]  # each task's step limit, in task order

    @property
    def total(self) -> float:
        return self.png + self.video + self.arrays

    def cheaper(self) -> str:
        """The flags that write less, largest saving first, with what each saves."""
        flags = [(self.png, "--png-every 0 (or N: every N-th step)"), (self.video, "--no-video")]
        named = [f"{flag}: -{size_text(size)}" for size, flag in sorted(flags, reverse=True) if size > 0]
        if self.png > 0:
            named.append("--layers -1 (one layer's panels)")
        return ", ".join(named + ["--max-steps N", "fewer --episodes", "--out on a larger disk"])


def estimate(protocol, shape: ModelShape, jobs: Iterable, steps: int | None = None) -> Estimate:
    """What `jobs` (EpisodeJob) of `protocol` write, each episode `steps` steps or up to its task's limit."""
    jobs = list(jobs)
    tasks = list(dict.fromkeys(job.task for job in jobs))
    limit = {task: steps if steps is not None else task_steps(protocol, task) for task in tasks}
    per_task = {task: episode_bytes(protocol, task, shape, limit[task]) for task in tasks}
    sums = {kind: sum(per_task[job.task][kind] for job in jobs) for kind in ("png", "video", "arrays")}
    return Estimate(sums["png"], sums["video"], sums["arrays"] + (RUN_BYTES if jobs else 0), len(jobs),
                    tuple(limit.values()))


def _steps_text(e: Estimate) -> str:
    low, high = min(e.steps), max(e.steps)
    return f"{low}" if low == high else f"{low}-{high}"


def check_space(protocol, model, jobs, run_dir: str | os.PathLike) -> Estimate | None:
    """Refuse (NotEnoughSpace, one line) when what `jobs` write exceeds the free space where the run writes."""
    jobs = list(jobs)
    if not jobs:
        return None
    found = estimate(protocol, ModelShape.of(model), jobs)
    free = free_bytes(run_dir)
    if found.total > free:
        raise NotEnoughSpace(
            f"the {found.episodes} episode(s) to run need up to {size_text(found.total)} (each up to its step limit of "
            f"{_steps_text(found)}: PNG {size_text(found.png)}, video {size_text(found.video)}, arrays "
            f"{size_text(found.arrays)}) but {size_text(free)} are free under {run_dir}; write less with "
            f"{found.cheaper()}; or pass --no-space-check to start anyway")
    return found


def full_disk(run_dir, cause: str, protocol, model, jobs_left) -> DiskFullError:
    """The one line of a run stopped by a full disk: the folder, what the episodes left need and what is free."""
    jobs_left = list(jobs_left)
    needed = estimate(protocol, ModelShape.of(model), jobs_left).total if jobs_left and model is not None else 0
    return DiskFullError(
        f"the disk under {run_dir} is full ({cause}); the run stopped: {len(jobs_left)} episode(s) left, which need "
        f"up to {size_text(needed)} ({size_text(free_bytes(run_dir))} free now); free space, then run the same "
        "command again to resume (it runs the interrupted episodes again)")


@contextmanager
def stops_when_full(run_dir, protocol, model, jobs, done, row=None):
    """Around the driver's writes for one row: a write the disk refuses (results.jsonl, the manifest), or a row whose
    disk filled (lost part DISK), stops the run with `full_disk`, naming the `jobs` whose key is not in `done`."""

    def left():
        return [job for job in jobs if job.key not in done]

    try:
        yield
    except (OSError, RuntimeError) as exc:  # ResultsWriteError is a RuntimeError naming the OS error
        found = disk_error(exc)
        if found is None:
            raise
        raise full_disk(run_dir, f"{type(found).__name__}: {found}", protocol, model, left()) from exc
    if row is not None and row.lost == DISK:
        raise full_disk(run_dir, f"{row.directory}: {row.error}", protocol, model, left())

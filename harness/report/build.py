"""`octo-harness report`: read runs, aggregate attention per task, draw figures, write report.html + tables + plots.

A run of a policy without attention (RunRecord.attention False) shows its success, episodes and videos; its attention
figures and tables are left out and the page says so in one line (harness.analysis.runs.no_attention_line).

Pipeline: load_run (metadata) -> per finished episode: the measures stored in attention.npz (older runs: measured
from readout_attention, in worker processes when large) -> summary (harness.analysis.aggregate) -> per run and
task: bootstrap tables (harness.report.rundata) -> overlay grids (videos decoded in background threads) ->
page (harness.report.page) -> files. Output folder:

  report.html        one self-contained file (images inlined as base64 PNG, videos linked relatively)
  tables/layers.csv  long format: run, task, layer, head ("mean"), metric, value, ci_low, ci_high, outcome, n
  tables/heads.csv   the same per head (integer head)
  tables/progress.csv  per layer along normalised episode progress (+ bin, progress_from, progress_to)
  tables/success.csv   per run and task: episodes, errors, missing, successes, rate and Wilson interval
  tables/episodes.csv  one row per finished job (status, success, steps, headline lift, error)
  tables/faithfulness.csv, interventions.csv   harness/report/faithfulness.py
  tables/phase_*.csv   task phases: phase x layer table, steps, tests, event-aligned views, failures (report/phases.py)
  tables/position_bound.csv, position_share.csv, position_lift.csv   attention controls (report/position.py)
  tables/grounding_*.csv  LIBERO-Object runs: object picked vs named, named-object lift per layer (report/grounding.py)
  tables/failures.csv  runs with a failed episode: diagnose's rows, one per failed episode (report/failures.py)
  tables/robustness*.csv  when a run was perturbed: success per task x condition x level, episode measures,
                     step-0 attention shift against the nominal episode, nuisance-success association
  plots/*.png        every figure of the page

The folder is built under a temporary name next to `out` and swapped in at the end, so a report folder is
never half-written or mixed with an older report's files.
"""

from __future__ import annotations

import io
import math
import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from harness.bounded import open_npz
from harness.interrupts import die_with_parent
from harness.analysis import aggregate as agg
from harness.measures.episode import MEASURES, episode_measures, measures_from_arrays
from harness.analysis.runs import EpisodeRecord, RunRecord, load_episode_arrays, load_run
from harness.measures.stats import success_summary
from harness.report import faithfulness, figures, page
from harness.report.frames import VIDEO_DISPLAY, read_video_frames
from harness.report.rundata import RunData, episode_headline, representative
from harness.report.rundata import csv_bytes as _csv
from harness.report.sections import sections


class ReportError(ValueError):
    """A user error while building a report (one line)."""


@dataclass(frozen=True)
class ReportOptions:
    bins: int = 10  # bins of normalised episode progress
    resamples: int = 2000  # bootstrap resamples
    confidence: float = 0.95
    seed: int = 0  # bootstrap seed (same seed -> same intervals)
    workers: int | None = None  # processes measuring older runs' attention; None = up to 4 above 1 GB, else none
    overlay_steps: int = 6  # time columns of the overlay grid
    overlay_layers: int = 12  # at most this many layers in the overlay grid (evenly spaced, first and last kept)
    margin: float = 0.15  # a robustness cell HOLDS when a drop larger than this is ruled out

    def __post_init__(self) -> None:
        if not 0 < self.margin < 1:
            raise ReportError(f"--margin must be between 0 and 1 (a drop in success rate, e.g. 0.15), got {self.margin}")
        if self.bins < 1 or self.resamples < 1 or self.overlay_steps < 1 or self.overlay_layers < 1:
            raise ReportError("bins, resamples, overlay steps and overlay layers must be >= 1")
        if not 0 < self.confidence < 1:
            raise ReportError(f"confidence must be between 0 and 1, got {self.confidence}")
        if self.workers is not None and self.workers < 1:
            raise ReportError(f"workers must be >= 1, got {self.workers}")


# ---- episode analysis (runs in worker processes) ----------------------------------------------------------------


def _analyse_episode(job: tuple, stored_only: bool = False) -> tuple[int, str, int, agg.EpisodeSummary | None, str | None]:
    """(run index, task, episode, episode dir, bins) -> (run index, task, episode, summary or None, error or None).

    Reads the measures the writers stored (a few MB); without them (older runs) measures the readout attention,
    unless `stored_only` (then summary and error are both None: the caller measures it later, maybe in a pool).
    """
    from harness.octo.tokens import TokenMap

    run_index, task, episode, directory, bins = job
    record = EpisodeRecord(task=task, episode=episode, seed=None, status="ok", success=False, steps=0, directory=Path(directory))
    try:
        with open_npz(record.attention_path) as z:
            measures = measures_from_arrays({k: z[k] for k in z.files if k.startswith(MEASURES)})
        if measures is None:
            if stored_only:
                return run_index, task, episode, None, None
            arrays = load_episode_arrays(record)
            measures = episode_measures(arrays.readout_attention, TokenMap.from_arrays(arrays.tokens),
                                            arrays.mask_fractions, arrays.mask_areas, arrays.mask_mass)
        return run_index, task, episode, agg.summarise_episode(measures, bins), None
    except Exception as exc:  # noqa: BLE001 - one unreadable episode is reported, the report goes on
        return run_index, task, episode, None, f"{type(exc).__name__}: {exc}"


def _analyse_all(runs: list[RunData], options: ReportOptions) -> None:
    jobs = [(i, e.task, e.episode, str(e.directory), options.bins)  # a run without attention has none to analyse
            for i, run in enumerate(runs) if run.record.attention for e in run.record.episodes if e.ok]
    results = [_analyse_episode(job, stored_only=True) for job in jobs]
    todo = [job for job, (_, _, _, summary, error) in zip(jobs, results) if summary is None and error is None]
    heavy = sum(Path(job[3], "attention.npz").stat().st_size for job in todo) > 1e9  # worth starting processes
    workers = options.workers or (max(1, min(4, os.cpu_count() or 1)) if heavy else 1)
    if todo and (workers == 1 or len(todo) == 1):
        results += [_analyse_episode(job) for job in todo]
    elif todo:  # older runs: the attention arrays are measured in parallel processes
        with ProcessPoolExecutor(max_workers=min(workers, len(todo)), mp_context=get_context("spawn"),
                                 initializer=die_with_parent) as pool:
            results += list(pool.map(_analyse_episode, todo, chunksize=1))
    for run_index, task, episode, summary, error in results:
        if summary is not None:
            runs[run_index].summaries[(task, episode)] = summary
        elif error is not None:
            runs[run_index].errors[(task, episode)] = error


def _aggregate(run: RunData, options: ReportOptions) -> None:
    names: set[str] = set()
    for s in run.summaries.values():
        names.update(s.layer)
    first = next(iter(run.summaries.values()), None)
    run.cameras = _cameras(run)
    run.headline = agg.headline_metric(names, run.cameras) if first else None
    for task in run.record.tasks:
        episodes = [e for e in run.record.task_episodes(task) if e.ok]
        analysed = [e for e in episodes if (task, e.episode) in run.summaries]
        tables = agg.aggregate_task([run.summaries[(task, e.episode)] for e in analysed], [e.success for e in analysed],
                                    run.label, task, options.confidence, options.resamples, options.seed)
        for key, rows in tables.items():
            run.rows[key].extend(rows)
        all_episodes = run.record.task_episodes(task)
        summary = success_summary(sum(e.success for e in episodes), len(episodes), method="wilson",
                                  confidence=options.confidence)
        summary.update(errored=sum(not e.ok for e in all_episodes), missing=run.record.missing_by_task().get(task, 0),
                       jobs=sum(t == task for t, _, _ in run.record.jobs), analysed=len(analysed))
        run.success[task] = summary
    run.build_index()


def _cameras(run: RunData) -> list[str]:
    """Observation keys of the model's image groups, in token order (from any analysed episode)."""
    for (task, episode) in run.summaries:
        path = next(e for e in run.record.episodes if (e.task, e.episode) == (task, episode)).attention_path
        try:
            with open_npz(path) as z:
                return [str(k) for k in z["tokens/image_keys"]]
        except (OSError, KeyError, ValueError):
            continue
    return []


# ---- overlays of a representative episode -----------------------------------------------------------------------


def _evenly(n: int, k: int) -> list[int]:
    """k evenly spaced indices of range(n), first and last included, unique."""
    if n <= k:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, k)})


def _patch_box(coverage: np.ndarray) -> tuple[float, float, float, float] | None:
    """coverage (rows, cols) -> (top, left, bottom, right) as fractions of the image around the covered patches."""
    inside = np.nan_to_num(coverage) > 0
    if not inside.any():
        return None
    ys, xs = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
    rows, cols = coverage.shape
    return ys[0] / rows, xs[0] / cols, (ys[-1] + 1) / rows, (xs[-1] + 1) / cols


def _overlay_png(run: RunData, episode: EpisodeRecord, options: ReportOptions) -> tuple[bytes, str] | None:
    from harness.measures.attention import camera_maps
    from harness.octo.tokens import TokenMap

    try:
        arrays = load_episode_arrays(episode)
    except (OSError, ValueError, KeyError):
        return None
    tokens = TokenMap.from_arrays(arrays.tokens)
    attn = arrays.readout_attention  # (steps, layers, heads, readouts, keys)
    steps, layers = attn.shape[:2]
    if steps == 0 or not tokens.image_groups:
        return None
    meta = episode.read_json()
    chosen = (meta.get("options") or {}).get("video_camera")  # a key, the keys of the video's rows, or null (every camera)
    chosen = chosen[0] if isinstance(chosen, list) and chosen else chosen
    video_camera = chosen if isinstance(chosen, str) else tokens.image_groups[0][1]  # the MP4's first row
    picked = _evenly(steps, options.overlay_steps)
    shown_layers = _evenly(layers, options.overlay_layers)
    rows = attn[picked].astype(np.float32).mean(axis=(2, 3))  # (t, layers, keys): head and readout mean
    last = attn[:, -1].astype(np.float32).mean(axis=(1, 2))  # (steps, keys): last layer, head and readout mean
    total = last.sum(axis=-1)
    step_numbers = [int(arrays.step[i]) for i in picked]
    faith = faithfulness.summarise([r for r in faithfulness.read_rows(run) if r["task"] == episode.task], run.label)
    panels, notes = [], []
    for group, camera, grid_rows, grid_cols in tokens.image_groups:  # every camera the model reads, side by side
        maps = camera_maps(rows, tokens, camera)[:, shown_layers].transpose(1, 0, 2, 3)  # (layers, t, rows, cols)
        frames: dict[int, np.ndarray] = {}
        if episode.video_path is not None and camera == video_camera:  # the MP4 holds the video camera's frames
            width = max(1, int(round(VIDEO_DISPLAY * grid_cols / grid_rows)))
            by_index = read_video_frames(episode.video_path, picked, VIDEO_DISPLAY, width)
            frames = {step_numbers[j]: by_index[i] for j, i in enumerate(picked) if i in by_index}
        share = float(np.mean(last[:, tokens.group == group].sum(axis=-1) / np.where(total > 0, total, 1)))
        title = (f"{run.label} | {episode.task} ep. {episode.episode} | {camera} | {share:.0%} of the last layer's "
                 "readout attention | head mean (each cell its own range) | green: target patches")
        coverage = arrays.mask_fractions.get(f"{camera}/target")  # (steps, rows, cols) or None
        boxes = [_patch_box(coverage[i]) if coverage is not None else None for i in picked]
        panels.append(figures.overlay_grid([frames.get(s) for s in step_numbers], maps, shown_layers, step_numbers,
                                           title, boxes))
        note = f"{camera}: {share:.0%} of the last layer's readout attention"
        ranked = [r for r in faith if r[2] == camera and r[3] != "random" and math.isfinite(r[7])]
        if ranked:
            best = max(ranked, key=lambda r: r[7])
            note += f", most faithful: {best[3]} (deletion {best[7]:.2f}x random [{best[8]:.2f}, {best[9]:.2f}])"
        if not frames:
            note += (" (maps without the camera image: no rollout.mp4)" if episode.video_path is None else
                     f" (maps without the camera image: the MP4 shows {video_camera})" if camera != video_camera else
                     " (maps without the camera image: rollout.mp4 unreadable)")
        notes.append(note)
    return _side_by_side(panels), f"episode {episode.episode}; " + "; ".join(notes)


def _side_by_side(pngs: list[bytes]) -> bytes:
    """PNG images placed left to right on white (top-aligned)."""
    from PIL import Image

    if len(pngs) == 1:
        return pngs[0]
    images = [Image.open(io.BytesIO(p)).convert("RGB") for p in pngs]
    canvas = Image.new("RGB", (sum(i.width for i in images), max(i.height for i in images)), "white")
    x = 0
    for image in images:
        canvas.paste(image, (x, 0))
        x += image.width
    out = io.BytesIO()
    canvas.save(out, format="PNG")
    return out.getvalue()


# ---- tables --------------------------------------------------------------------------------------------------------




def _tables(runs: list[RunData], summaries: dict | None = None) -> dict[str, bytes]:
    success_cols = ("run", "task", "jobs", "missing", "errored", "n", "successes", "success_rate", "ci_low", "ci_high", "method")
    success_rows = [(run.label, t, s["jobs"], s["missing"], s["errored"], s["n"], s["successes"], s["success_rate"],
                     s["ci_low"], s["ci_high"], s["method"]) for run in runs for t, s in run.success.items()]
    episode_cols = ("run", "task", "episode", "seed", "status", "success", "steps", "analysed", "headline_metric",
                    "headline_last_layer", "error", "directory")
    episode_rows = []
    for run in runs:
        for e in run.record.episodes:
            analysed = (e.task, e.episode) in run.summaries
            error = e.error if not e.ok else run.errors.get((e.task, e.episode), "")
            episode_rows.append((run.label, e.task, e.episode, e.seed, e.status, e.success, e.steps, analysed,
                                 run.headline or "", episode_headline(run, e), error or "", str(e.directory)))
    return {
        "layers.csv": _csv(agg.TABLE_COLUMNS, [r for run in runs for r in run.rows["layers"]]),
        "heads.csv": _csv(agg.TABLE_COLUMNS, [r for run in runs for r in run.rows["heads"]]),
        "progress.csv": _csv(agg.PROGRESS_COLUMNS, [r for run in runs for r in run.rows["progress"]]),
        "success.csv": _csv(success_cols, success_rows),
        "episodes.csv": _csv(episode_cols, episode_rows),
        # each section's files (harness/report/sections.py): faithfulness, phase_*, position_*, robustness*, grounding_*
        **{name: data for s in sections() for name, data in s.tables(runs, (summaries or {}).get(s.anchor)).items()},
    }


# ---- entry point ---------------------------------------------------------------------------------------------------


def _labels(records: list[RunRecord]) -> list[str]:
    names = [r.name for r in records]
    return [f"{r.path.parent.name}/{r.name}" if names.count(r.name) > 1 else r.name for r in records]


def _check_out(out: Path, runs: list[RunRecord]) -> None:
    if out.exists() and not out.is_dir():
        raise ReportError(f"--out {out} is a file; choose a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "report.html").is_file():
        raise ReportError(f"refusing to replace {out}: it is not a report folder (no report.html); choose another --out")
    for r in runs:
        if out.resolve() == r.path:
            raise ReportError(f"--out {out} is a run folder; choose another folder (default: RUN_DIR/report)")


def _remove_stale_staging(out: Path) -> None:
    """Delete `.<out>.tmp-<pid>` / `.<out>.old-<pid>` folders left by report processes that no longer run."""
    for path in out.parent.glob(f".{out.name}.*-*"):
        kind, _, pid = path.name[len(out.name) + 2:].partition("-")
        if kind not in ("tmp", "old") or not pid.isdigit():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
        except PermissionError:  # another user's live process
            pass


@dataclass(frozen=True)
class ReportResult:
    out: Path
    html: Path
    tables: tuple[str, ...]
    plots: tuple[str, ...]
    seconds: float
    episodes: int  # episodes analysed


def build_report(run_dirs: list[str | Path], out: str | Path | None = None, options: ReportOptions | None = None) -> ReportResult:
    """Build the report of one or more runs into `out` (default: <first run>/report). Returns what was written."""
    start = time.perf_counter()
    options = options or ReportOptions()
    if not run_dirs:
        raise ReportError("give at least one run folder")
    records = [load_run(p) for p in run_dirs]  # NotARunError (one line) before anything heavy
    out = Path(out) if out is not None else records[0].path / "report"
    out = out.resolve()
    _check_out(out, records)
    runs = [RunData(record=r, label=label, colour=colour)
            for r, label, colour in zip(records, _labels(records), figures.run_colours(len(records)))]
    _analyse_all(runs, options)
    for run in runs:
        _aggregate(run, options)
    tasks = list(dict.fromkeys(t for run in runs for t in run.record.tasks))
    summaries = {s.anchor: s.summarise(runs, options) for s in sections()}  # each read once, for tables and page

    with ThreadPoolExecutor(max_workers=3) as pool:  # overlay grids decode videos in ffmpeg processes meanwhile
        overlays = {}
        for run in runs:
            for task in run.record.tasks:
                rep = representative(run, task)
                if rep is not None:
                    overlays[(run.label, task)] = pool.submit(_overlay_png, run, rep, options)
        document, plot_files = page.render(runs, tasks, out, overlays, summaries)

    tables = _tables(runs, summaries)
    _remove_stale_staging(out)
    staging = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    try:
        (staging / "tables").mkdir(parents=True)
        (staging / "plots").mkdir()
        for name, data in tables.items():
            (staging / "tables" / name).write_bytes(data)
        for name, data in plot_files.items():
            (staging / "plots" / name).write_bytes(data)
        (staging / "report.html").write_text(document, encoding="utf-8")
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        if out.exists():
            os.replace(out, old)
        os.replace(staging, out)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return ReportResult(out=out, html=out / "report.html", tables=tuple(sorted(tables)), plots=tuple(sorted(plot_files)),
                        seconds=time.perf_counter() - start, episodes=sum(len(r.summaries) for r in runs))

"""`octo-harness report`: read runs, aggregate attention per task, draw figures, write report.html + tables + plots.

Pipeline: load_run (metadata) -> per finished episode, in worker processes: attention.npz -> measures ->
summary (harness.analysis.aggregate) -> per run and task: bootstrap tables -> figures -> HTML. Output folder:

  report.html        one self-contained file (images inlined as base64 PNG, videos linked relatively)
  tables/layers.csv  long format: run, task, layer, head ("mean"), metric, value, ci_low, ci_high, outcome, n
  tables/heads.csv   the same per head (integer head)
  tables/progress.csv  per layer along normalised episode progress (+ bin, progress_from, progress_to)
  tables/success.csv   per run and task: episodes, errors, missing, successes, rate and Wilson interval
  tables/episodes.csv  one row per finished job (status, success, steps, headline lift, error)
  plots/*.png        every figure of the page

The folder is built under a temporary name next to `out` and swapped in at the end, so a report folder is
never half-written or mixed with an older report's files.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import os
import shutil
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from harness.analysis import aggregate as agg
from harness.analysis.runs import EpisodeRecord, RunRecord, load_episode_arrays, load_run
from harness.analysis.stats import success_summary
from harness.report import figures
from harness.report import html as H

VIDEO_DISPLAY = 256  # harness.overlays.video_frame's `display`: the camera frame fills the video's top-left display x w
SHARE_COLOURS = {"primary": "#4c72b0", "wrist": "#55a868", "language": "#c44e52", "readout": "#8172b2",
                 "proprio": "#ccb974", "other": "#999999", "earlier timesteps": "#64b5cd"}


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

    def __post_init__(self) -> None:
        if self.bins < 1 or self.resamples < 1 or self.overlay_steps < 1 or self.overlay_layers < 1:
            raise ReportError("bins, resamples, overlay steps and overlay layers must be >= 1")
        if not 0 < self.confidence < 1:
            raise ReportError(f"confidence must be between 0 and 1, got {self.confidence}")
        if self.workers is not None and self.workers < 1:
            raise ReportError(f"workers must be >= 1, got {self.workers}")


@dataclass
class RunData:
    """Everything the page needs about one run."""

    record: RunRecord
    label: str
    colour: str
    summaries: dict[tuple[str, int], agg.EpisodeSummary] = field(default_factory=dict)
    errors: dict[tuple[str, int], str] = field(default_factory=dict)  # episodes whose arrays could not be analysed
    rows: dict[str, list[tuple]] = field(default_factory=lambda: {"layers": [], "heads": [], "progress": []})
    success: dict[str, dict] = field(default_factory=dict)  # task -> success_summary(...) + counts
    headline: str | None = None  # e.g. mask_lift/image_primary/target
    cameras: list[str] = field(default_factory=list)

    def layer_values(self, task: str, metric: str, outcome: str = "all") -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        return self._index.get(("layers", task, outcome, metric))

    def head_values(self, task: str, metric: str, outcome: str = "all") -> np.ndarray | None:
        found = self._index.get(("heads", task, outcome, metric))
        return None if found is None else found[0]

    def progress_values(self, task: str, metric: str, layer: int, outcome: str = "all"):
        return self._index.get(("progress", task, outcome, metric, layer))

    def build_index(self) -> None:
        """(table, task, outcome, metric[, layer]) -> arrays, from the long rows."""
        index: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        grouped: dict[tuple, list[tuple]] = defaultdict(list)
        for r in self.rows["layers"]:
            grouped[("layers", r[1], r[8], r[4])].append(r)
        for key, rows in grouped.items():
            layers = max(r[2] for r in rows) + 1
            v, lo, hi = (np.full(layers, np.nan) for _ in range(3))
            for r in rows:
                v[r[2]], lo[r[2]], hi[r[2]] = r[5], r[6], r[7]
            index[key] = (v, lo, hi)
        grouped = defaultdict(list)
        for r in self.rows["heads"]:
            grouped[("heads", r[1], r[8], r[4])].append(r)
        for key, rows in grouped.items():
            shape = (max(r[2] for r in rows) + 1, max(r[3] for r in rows) + 1)
            v, lo, hi = (np.full(shape, np.nan) for _ in range(3))
            for r in rows:
                v[r[2], r[3]], lo[r[2], r[3]], hi[r[2], r[3]] = r[5], r[6], r[7]
            index[key] = (v, lo, hi)
        grouped = defaultdict(list)
        for r in self.rows["progress"]:
            grouped[("progress", r[1], r[8], r[4], r[2])].append(r)
        for key, rows in grouped.items():
            bins = max(r[10] for r in rows) + 1
            v, lo, hi = (np.full(bins, np.nan) for _ in range(3))
            for r in rows:
                v[r[10]], lo[r[10]], hi[r[10]] = r[5], r[6], r[7]
            index[key] = (v, lo, hi)
        self._index = index


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
        with np.load(record.attention_path) as z:
            measures = agg.measures_from_arrays({k: z[k] for k in z.files if k.startswith(agg.MEASURES)})
        if measures is None:
            if stored_only:
                return run_index, task, episode, None, None
            arrays = load_episode_arrays(record)
            measures = agg.episode_measures(arrays.readout_attention, TokenMap.from_arrays(arrays.tokens),
                                            arrays.mask_fractions, arrays.mask_areas, arrays.mask_mass)
        return run_index, task, episode, agg.summarise_episode(measures, bins), None
    except Exception as exc:  # noqa: BLE001 - one unreadable episode is reported, the report goes on
        return run_index, task, episode, None, f"{type(exc).__name__}: {exc}"


def _analyse_all(runs: list[RunData], options: ReportOptions) -> None:
    jobs = [(i, e.task, e.episode, str(e.directory), options.bins)
            for i, run in enumerate(runs) for e in run.record.episodes if e.ok]
    results = [_analyse_episode(job, stored_only=True) for job in jobs]
    todo = [job for job, (_, _, _, summary, error) in zip(jobs, results) if summary is None and error is None]
    heavy = sum(Path(job[3], "attention.npz").stat().st_size for job in todo) > 1e9  # worth starting processes
    workers = options.workers or (max(1, min(4, os.cpu_count() or 1)) if heavy else 1)
    if todo and (workers == 1 or len(todo) == 1):
        results += [_analyse_episode(job) for job in todo]
    elif todo:  # older runs: the attention arrays are measured in parallel processes
        with ProcessPoolExecutor(max_workers=min(workers, len(todo)), mp_context=get_context("spawn")) as pool:
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
            with np.load(path) as z:
                return [str(k) for k in z["tokens/image_keys"]]
        except (OSError, KeyError, ValueError):
            continue
    return []


# ---- overlays of a representative episode -----------------------------------------------------------------------


def read_video_frames(path: Path, indices: list[int], height: int, width: int) -> dict[int, np.ndarray]:
    """Frames `indices` of an MP4, cropped to the top-left height x width -> {index: (height, width, 3) uint8}.

    One ffmpeg pass with a select filter (only the chosen frames are converted); {} when the video is unreadable.
    """
    import imageio_ffmpeg

    if not indices:
        return {}
    select = "+".join(f"eq(n\\,{i})" for i in sorted(set(indices)))
    logger = logging.getLogger("imageio_ffmpeg")  # it warns that the cropped size differs from the video's: intended
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        reader = imageio_ffmpeg.read_frames(str(path), input_params=["-skip_loop_filter", "all"], output_params=[
            "-vf", f"select={select},crop={width}:{height}:0:0", "-fps_mode", "passthrough"])  # thumbnails: no deblocking
        meta = next(reader)
        if meta["source_size"][0] < width or meta["source_size"][1] < height:
            reader.close()
            return {}
        frames = [np.frombuffer(buf, np.uint8).reshape(height, width, 3).copy() for buf in reader]
    except (OSError, RuntimeError, StopIteration, ValueError):
        return {}
    finally:
        logger.setLevel(level)
    return dict(zip(sorted(set(indices)), frames))


def _evenly(n: int, k: int) -> list[int]:
    """k evenly spaced indices of range(n), first and last included, unique."""
    if n <= k:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, k)})


def _representative(run: RunData, task: str) -> EpisodeRecord | None:
    analysed = [e for e in run.record.task_episodes(task) if e.ok and (task, e.episode) in run.summaries]
    if not analysed:
        return None
    values = np.array([_episode_headline(run, e) for e in analysed])
    return analysed[agg.representative_index(values)]


def _episode_headline(run: RunData, e: EpisodeRecord) -> float:
    summary = run.summaries.get((e.task, e.episode))
    if summary is None or run.headline is None or run.headline not in summary.layer:
        return float("nan")
    return float(summary.layer[run.headline][-1])


def _overlay_png(run: RunData, episode: EpisodeRecord, options: ReportOptions) -> tuple[bytes, str] | None:
    from harness.attention import camera_maps
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
    camera = (meta.get("options") or {}).get("video_camera") or tokens.image_groups[0][1]
    if camera not in {k for _, k, _, _ in tokens.image_groups}:
        camera = tokens.image_groups[0][1]
    picked = _evenly(steps, options.overlay_steps)
    shown_layers = _evenly(layers, options.overlay_layers)
    rows = attn[picked].astype(np.float32).mean(axis=(2, 3))  # (t, layers, keys): head and readout mean
    maps = camera_maps(rows, tokens, camera)[:, shown_layers].transpose(1, 0, 2, 3)  # (layers, t, rows, cols)
    grid_rows, grid_cols = tokens.grid(tokens.camera_group(camera))
    frames: dict[int, np.ndarray] = {}
    video_camera = (meta.get("options") or {}).get("video_camera") or tokens.image_groups[0][1]
    if episode.video_path is not None and camera == video_camera:
        step_numbers = [int(arrays.step[i]) for i in picked]
        width = max(1, int(round(VIDEO_DISPLAY * grid_cols / grid_rows)))
        by_index = read_video_frames(episode.video_path, picked, VIDEO_DISPLAY, width)
        frames = {step_numbers[j]: by_index[i] for j, i in enumerate(picked) if i in by_index}
    step_numbers = [int(arrays.step[i]) for i in picked]
    title = f"{run.label} | {episode.task} episode {episode.episode} | {camera} | head-mean attention (each cell its own range)"
    png = figures.overlay_grid([frames.get(s) for s in step_numbers], maps, shown_layers, step_numbers, title)
    note = "" if frames else " (no rollout.mp4 frames: attention maps without the camera image)"
    return png, f"{camera}, episode {episode.episode}{note}"


# ---- page ------------------------------------------------------------------------------------------------------


def _metric_label(metric: str) -> str:
    parts = metric.split("/")
    if parts[0] == "mask_lift":
        return f"{parts[2]} lift ({parts[1]})"
    if parts[0] == "mask_mass":
        return f"{parts[2]} mass ({parts[1]})"
    if parts[0] == "share":
        return f"share: {parts[1]}"
    if parts[0] == "timestep_share":
        return f"share: {parts[1]} timestep" + ("s" if parts[1] == "earlier" else "")
    return metric


def _share_categories(runs: list[RunData]) -> list[tuple[str, str]]:
    """[(label, metric)] of the modality shares plus the earlier-timesteps share, in a fixed order."""
    metrics: list[str] = []
    for run in runs:
        for r in run.rows["layers"]:
            if r[4].startswith("share/") and r[4] not in metrics:
                metrics.append(r[4])
    order = ["primary", "wrist", "language", "readout"]
    metrics.sort(key=lambda m: (order.index(m[6:]) if m[6:] in order else len(order), m))
    out = [(m[6:], m) for m in metrics]
    if any(r[4] == "timestep_share/earlier" for run in runs for r in run.rows["layers"]):
        out.append(("earlier timesteps", "timestep_share/earlier"))
    return out


def _mask_metric(run: RunData, name: str) -> str | None:
    """mask_lift / mask_mass metric of a mask name on the headline camera."""
    if run.headline is None:
        return None
    return run.headline.replace("/target", f"/{name}")


def _last(values) -> float:
    return float(values[-1]) if values is not None and len(values) else float("nan")


def _task_table(runs: list[RunData], task: str) -> str:
    header = ["run", "episodes done / jobs", "missing", "errored", "success (95% Wilson)",
              "target lift, last layer", "robot mass, last layer", "entropy, last layer (nats)"]
    rows = []
    for run in runs:
        s = run.success.get(task)
        if s is None:
            rows.append([H.swatch(run.colour, run.label), H.absent("task not in this run"), "", "", "", "", "", ""])
            continue
        done = s["jobs"] - s["missing"]
        rate = (H.fmt_ci(s["success_rate"], s["ci_low"], s["ci_high"]) if s["n"] else H.absent("no finished episode"))
        cells = [H.swatch(run.colour, run.label), f"{done} / {s['jobs']}", s["missing"], s["errored"],
                 H.Raw(f"{s['successes']}/{s['n']} = {rate}") if s["n"] else rate]
        for metric in (run.headline, _mask_metric(run, "robot").replace("mask_lift", "mask_mass") if run.headline else None,
                       "entropy"):
            found = run.layer_values(task, metric) if metric else None
            if found is None:
                cells.append(H.absent("absent (no mask)" if metric != "entropy" else "n/a"))
            else:
                v, lo, hi = found
                cells.append(H.fmt_ci(v[-1], lo[-1], hi[-1]))
        rows.append(cells)
    return H.table(header, rows, numeric=(2, 3))


def _episode_rows(run: RunData, task: str, out: Path) -> tuple[str, str]:
    """(table html, videos html) for the episodes of a task."""
    rows, videos = [], []
    rep = _representative(run, task)
    for e in run.record.task_episodes(task):
        if not e.ok:
            note = H.Raw(f"<span style='color:#c0392b'>failed: {H.esc(e.error or 'error')}</span>")
        elif (task, e.episode) in run.errors:
            note = H.Raw(f"<span style='color:#c0392b'>not analysed: {H.esc(run.errors[(task, e.episode)])}</span>")
        else:
            note = "representative episode (overlays)" if rep is not None and e.episode == rep.episode else ""
        value = _episode_headline(run, e)
        rows.append([e.episode, "" if e.seed is None else e.seed, e.status, "yes" if e.success else "no", e.steps,
                     H.fmt(value) if math.isfinite(value) else H.absent("n/a"), note])
        if e.ok and e.video_path is not None:
            rel = os.path.relpath(e.video_path, out)
            videos.append(H.video(rel, f"episode {e.episode} (seed {e.seed}) — {'success' if e.success else 'no success'}"))
    table = H.table(["episode", "seed", "status", "success", "steps", "target lift (last layer, mean over steps)", "note"],
                    rows, numeric=(0, 1, 4, 5))
    return table, "".join(videos)


def _manifest_section(run: RunData) -> str:
    r = run.record
    parts = []
    if r.model.is_random:
        parts.append(H.banner(f"RANDOM WEIGHTS: {r.model.source} has random weights — its actions and attention are "
                              "not a trained policy's. This run checks the pipeline, not Octo's behaviour.", danger=True))
    protocol = r.manifest.get("protocol") or r.manifest
    execution = protocol.get("execution")
    pairs = [
        ("run", f"{r.name} ({r.path})"),
        ("format", r.format),
        ("status", f"{r.status}; {len(r.episodes)} of {len(r.jobs)} jobs finished, {r.missing} missing"),
        ("model", r.model.source + (" [RANDOM WEIGHTS]" if r.model.is_random else "")),
        ("model note", r.model.note or "—"),
        ("text tokenizer", r.model.text_tokenizer or "—"),
        ("dataset key (action statistics)", r.model.dataset_key or "none"),
        ("execution", execution if isinstance(execution, str) else (str(execution) if execution else "—")),
        ("tasks", ", ".join(r.tasks)),
        ("episodes per task, seed", f"{protocol.get('episodes', '?')}, {protocol.get('seed', '?')}"),
        ("max steps", protocol.get("max_steps") if protocol.get("max_steps") is not None else "task default"),
        ("created", r.created or "—"),
        ("git commit", r.git_commit or "—"),
        ("versions", ", ".join(f"{k} {v}" for k, v in sorted(r.versions.items())) or "—"),
    ]
    if "protocol_hash" in r.manifest:
        pairs.append(("protocol hash", r.manifest["protocol_hash"]))
    parts.append(H.key_values(pairs))
    return H.section(f"Manifest: {run.label}", "".join(parts), anchor=H.anchor_id("manifest-" + run.label), level=3)


def _status_banners(runs: list[RunData]) -> str:
    out = []
    for run in runs:
        r = run.record
        if r.model.is_random:
            out.append(H.banner(f"{run.label}: RANDOM WEIGHTS ({r.model.source}) — actions and attention are not a "
                                "trained policy's.", danger=True))
        if r.missing:
            per_task = ", ".join(f"{t}: {n}" for t, n in r.missing_by_task().items() if n)
            state = {"running": "is still running", "interrupted": "was interrupted"}.get(r.status, "is incomplete")
            out.append(H.banner(f"{run.label} {state}: {r.missing} of {len(r.jobs)} episodes missing ({per_task}). "
                                f"This report shows the {len(r.episodes)} finished episodes."))
        failed = [e for e in r.episodes if not e.ok]
        if failed:
            out.append(H.banner(f"{run.label}: {len(failed)} episode(s) failed with an error (listed per task); they "
                                "have no attention and are left out of success rates and attention statistics."))
        if run.errors:
            out.append(H.banner(f"{run.label}: {len(run.errors)} finished episode(s) could not be analysed "
                                "(listed per task)."))
        if run.summaries and run.headline is None:
            out.append(H.banner(f"{run.label} recorded no target masks: target and robot metrics are absent "
                                "(not zero). Run without --no-masks to get them."))
    return "".join(out)


class _Plots:
    """Collects figure PNGs: written to plots/<name>.png and inlined in the page."""

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}

    def add(self, name: str, png: bytes, alt: str, caption: str) -> str:
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
        self.files[safe + ".png"] = png
        return H.image(png, alt, caption + f" (plots/{safe}.png)")


def _cross_task(runs: list[RunData], tasks: list[str], plots: _Plots) -> str:
    body = []
    series = []
    for run in runs:
        data = {t: (s["success_rate"], s["ci_low"], s["ci_high"], s["n"]) for t, s in run.success.items()}
        series.append((run.label, run.colour, data))
    body.append(plots.add("success_by_task", figures.success_chart(tasks, series), "success rate per task",
                          "Success rate per task with 95% Wilson intervals (finished, non-errored episodes; n above "
                          "each bar)."))
    panels = []
    for run in runs:
        layers = max((s.layers for s in run.summaries.values()), default=0)
        matrix = np.full((len(tasks), max(layers, 1)), np.nan)
        for i, t in enumerate(tasks):
            found = run.layer_values(t, run.headline) if run.headline else None
            if found is not None:
                matrix[i, : len(found[0])] = found[0]
        panels.append((run.label, run.colour, matrix))
    if any(np.isfinite(m).any() for _, _, m in panels):
        body.append(plots.add("target_lift_task_layer", figures.task_layer_heatmaps(tasks, panels, "target lift (1 = chance)"),
                              "target lift per task and layer",
                              "Target lift (attention mass on the target mask / mask area; 1 = chance, blue below, red "
                              "above) per task and layer, mean over episodes; grey n/a = absent."))
    else:
        body.append(H.note("Target lift: absent — no run recorded target masks."))
    categories = _share_categories(runs)
    share_panels = []
    for run in runs:
        layers = max((s.layers for s in run.summaries.values()), default=1)
        data = {}
        for label, metric in categories:
            matrix = np.full((len(tasks), max(layers, 1)), np.nan)
            for i, t in enumerate(tasks):
                found = run.layer_values(t, metric)
                if found is not None:
                    matrix[i, : len(found[0])] = found[0]
            data[label] = matrix
        share_panels.append((run.label, run.colour, data))
    if categories:
        body.append(plots.add("modality_shares_task_layer",
                              figures.shares_heatmaps(tasks, [c for c, _ in categories], share_panels),
                              "modality shares per task and layer",
                              "Share of the readout's attention per token group (rows) by task and layer, mean over "
                              "episodes; 'earlier timesteps' is the share on observation history (a separate split)."))
    prog: dict[str, list] = {}
    for t in tasks:
        prog[t] = []
        for run in runs:
            if not run.headline:
                continue
            layers = max((s.layers for s in run.summaries.values()), default=0)
            found = run.progress_values(t, run.headline, layers - 1)
            if found is not None:
                x = (np.arange(len(found[0])) + 0.5) / len(found[0])
                prog[t].append((run.label, run.colour, x, *found))
    if any(prog.values()):
        body.append(plots.add("target_lift_progress", figures.progress_small_multiples(tasks, prog, "target lift, last layer"),
                              "target lift along episode progress",
                              "Target lift at the last layer along normalised episode progress (bins of step / steps), "
                              "mean over episodes with 95% bootstrap bands; dotted line = chance."))
    legend = " ".join(H.swatch(r.colour, r.label) for r in runs)
    return H.section("Cross-task comparison", H.Raw(f"<p>{legend}</p>") + "".join(body), anchor="cross-task")


def _task_section(runs: list[RunData], task: str, out: Path, plots: _Plots, overlays: dict) -> str:
    body = [_task_table(runs, task)]
    safe = H.anchor_id(task)[2:]
    for run in runs:
        if task not in run.record.tasks:
            continue
        future = overlays.get((run.label, task))
        if future is not None:
            overlay = future.result()
            if overlay is not None:
                body.append(plots.add(f"overlays_{safe}_{run.label}", overlay[0], f"overlays {task} {run.label}",
                                      f"{run.label}: layer x time grid of head-mean readout attention over {overlay[1]}; "
                                      "the representative episode is the one whose target lift (last layer) is closest "
                                      "to the task's median (the first analysed episode without masks)."))
    head_panels = []
    for run in runs:
        matrix = run.head_values(task, run.headline) if run.headline else None
        if matrix is not None:
            head_panels.append((run.label, run.colour, matrix))
    if head_panels:
        body.append(plots.add(f"head_layer_lift_{safe}", figures.head_layer_maps(head_panels, "target lift (1 = chance)"),
                              f"target lift per head {task}",
                              "Target lift per layer and head (which heads follow the object), mean over episodes."))
    else:
        body.append(H.note("Target lift per head: absent (no target mask coverage recorded for this task)."))
    lines = []
    for run in runs:
        if not run.headline:
            continue
        layers = max((s.layers for s in run.summaries.values()), default=0)
        for outcome in ("success", "no_success"):
            found = run.progress_values(task, run.headline, layers - 1, outcome)
            if found is not None:
                x = (np.arange(len(found[0])) + 0.5) / len(found[0])
                lines.append((run.label, run.colour, outcome, x, *found))
    if lines:
        body.append(plots.add(f"target_lift_progress_{safe}", figures.progress_by_outcome(lines, "target lift, last layer"),
                              f"target lift along progress {task}",
                              "Target lift at the last layer along episode progress, successful (solid) vs "
                              "unsuccessful (dashed) episodes, 95% bootstrap bands."))
    share_panels = []
    for run in runs:
        data = {}
        for label, metric in _share_categories([run]):
            if metric.startswith("share/"):
                found = run.layer_values(task, metric)
                if found is not None:
                    data[label] = found[0]
        if data:
            share_panels.append((run.label, run.colour, data))
    if share_panels:
        body.append(plots.add(f"modality_shares_{safe}", figures.shares_by_layer(share_panels, SHARE_COLOURS),
                              f"modality shares {task}", "Modality shares of the readout attention along layers."))
    for run in runs:
        if task not in run.record.tasks:
            continue
        table, videos = _episode_rows(run, task, out)
        body.append(H.section(f"Episodes: {run.label}", table + (H.details(f"videos ({run.label})", H.Raw(
            f"<div class='videos'>{videos}</div>"), open_=False) if videos else H.note("no rollout.mp4 in this run")),
            level=3))
    return H.section(f"Task: {task}", "".join(body), anchor=H.anchor_id("task-" + task))


# ---- tables --------------------------------------------------------------------------------------------------------


def _csv(columns, rows) -> bytes:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow(["" if (isinstance(v, float) and not math.isfinite(v)) else (f"{v:.6g}" if isinstance(v, float) else v)
                         for v in row])
    return buffer.getvalue().encode()


def _tables(runs: list[RunData]) -> dict[str, bytes]:
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
                                 run.headline or "", _episode_headline(run, e), error or "", str(e.directory)))
    return {
        "layers.csv": _csv(agg.TABLE_COLUMNS, [r for run in runs for r in run.rows["layers"]]),
        "heads.csv": _csv(agg.TABLE_COLUMNS, [r for run in runs for r in run.rows["heads"]]),
        "progress.csv": _csv(agg.PROGRESS_COLUMNS, [r for run in runs for r in run.rows["progress"]]),
        "success.csv": _csv(success_cols, success_rows),
        "episodes.csv": _csv(episode_cols, episode_rows),
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

    plots = _Plots()
    body = [_status_banners(runs), H.Raw("<p class='note'>Every number here comes from the CSV files in "
                                         "<code>tables/</code> next to this page; intervals are 95% (Wilson for success, "
                                         "percentile bootstrap over episodes for attention).</p>")]
    with ThreadPoolExecutor(max_workers=3) as pool:  # overlay grids decode videos in ffmpeg processes meanwhile
        overlays = {}
        for run in runs:
            for task in run.record.tasks:
                rep = _representative(run, task)
                if rep is not None:
                    overlays[(run.label, task)] = pool.submit(_overlay_png, run, rep, options)
        body.append(_cross_task(runs, tasks, plots))
        for task in tasks:
            body.append(_task_section(runs, task, out, plots, overlays))
    body.append(H.section("Run manifest", "".join(_manifest_section(run) for run in runs), anchor="manifest"))
    body.append(H.section("Definitions", H.Raw(_DEFINITIONS), anchor="definitions"))
    toc = [("cross-task", "Cross-task comparison")] + [(H.anchor_id("task-" + t), t) for t in tasks] + [
        ("manifest", "Run manifest"), ("definitions", "Definitions")]
    title = "Attention report: " + " vs ".join(run.label for run in runs)
    subtitle = (f"{len(runs)} run(s), {len(tasks)} task(s), {sum(len(r.summaries) for r in runs)} episodes analysed; "
                f"generated {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    document = H.page(title, "".join(body), subtitle, toc, footer="octo-harness report")

    tables = _tables(runs)
    _remove_stale_staging(out)
    staging = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    try:
        (staging / "tables").mkdir(parents=True)
        (staging / "plots").mkdir()
        for name, data in tables.items():
            (staging / "tables" / name).write_bytes(data)
        for name, data in plots.files.items():
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
    return ReportResult(out=out, html=out / "report.html", tables=tuple(sorted(tables)), plots=tuple(sorted(plots.files)),
                        seconds=time.perf_counter() - start, episodes=sum(len(r.summaries) for r in runs))


_DEFINITIONS = """
<ul>
<li><b>Readout attention</b>: the post-softmax attention rows of the last timestep's readout token(s) over every key,
per layer and head (what the action head reads from). Head-mean values use the mean row over heads and readouts,
as in <code>metrics.jsonl</code>.</li>
<li><b>Modality share</b>: fraction of a row's mass on a token group (primary camera, wrist camera, language, readouts,
other groups such as proprio); the groups partition the keys, so shares sum to 1. <b>Earlier timesteps</b>: the
fraction on the observation history (all groups of earlier window steps), a separate split.</li>
<li><b>Target mass</b>: the fraction of the camera's current-timestep attention inside the target's segmentation mask
(each patch weighted by the share of its pixels in the mask). <b>Target lift</b> = target mass / mask area: 1 is
chance (uniform attention), 1/area means all attention on the target. Steps where the target is not visible have no
value. <b>Robot mass</b>: the same for the robot's mask.</li>
<li><b>Entropy</b>: entropy (nats) of each attention row, mean over heads and readouts.</li>
<li><b>Episode progress</b>: step t of an n-step episode falls in bin floor(t &middot; bins / n); values are averaged per
episode and bin, then over episodes.</li>
<li><b>Intervals</b>: success: Wilson score interval over non-errored episodes. Attention: 95% percentile bootstrap over
episodes (2000 resamples by default, fixed seed); one episode gives no interval. Outcome splits: successful vs
unsuccessful episodes.</li>
</ul>
"""

"""Time `octo-harness report` on generated run folders in the real format (default: 13 tasks x 10 episodes x 300 steps).

Each episode folder holds what the writers leave: attention.npz (readout_attention (steps, 12, 12, 1, 690) float16
with the octo-small-1.5 token layout, tokens/*, metrics/* and mask_fraction/* for the target and robot masks of
both cameras), actions.npz, metrics.jsonl, episode.json and rollout.mp4 (one real H.264 video in the writers'
frame layout, hard-linked into every episode) and the per-step measures the writers store (measures/*, computed
with the same function); the run has manifest.json, results.jsonl and results.json. 12 heads
is octo-base's head count (octo-small has 6): the heavier case. Attention rows are random Dirichlet-like rows with a
bias towards a moving target, so statistics are not degenerate.

    .venv/bin/python benchmarks/bench_report.py [--tasks 13 --episodes 10 --steps 300] [--workers N] [--keep DIR]

Prints the generated data size, the report's wall time (target <= 60 s) and episodes per second.
`--without-measures` generates episodes as runs made before the writers stored measures/*: the report then
reads and measures all of the attention (in worker processes).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from harness.measures.episode import measure_arrays
from harness.measures.attention import camera_keys
from harness.octo.tokens import build_token_map
from harness.outputs.overlays import heatmap_overlay, video_frame
from harness.report.build import ReportOptions, build_report
from harness.outputs.video import Mp4Writer

LAYERS, READOUTS = 12, 1
TOKENS = build_token_map(
    [("task_language", 16)],
    [("obs_primary", 256), ("obs_wrist", 64), ("obs_task_language", 16), ("readout_action", 1)],
    window=2,
    image_groups=(("obs_primary", "image_primary", 16, 16), ("obs_wrist", "image_wrist", 8, 8)),
)
TASKS = ("Lift", "Stack", "PickPlaceCan", "PickPlaceMilk", "PickPlaceBread", "PickPlaceCereal", "PickPlace",
         "NutAssemblySquare", "NutAssemblyRound", "NutAssembly", "Door", "Wipe", "ToolHang")


def _box_fraction(steps: int, rows: int, cols: int, centre: np.ndarray, size: float) -> np.ndarray:
    """(steps, rows, cols) coverage of an axis-aligned box (in patch units) around a moving centre."""
    y = np.arange(rows)[None, :, None]
    x = np.arange(cols)[None, None, :]
    cy, cx = centre[:, 0, None, None], centre[:, 1, None, None]
    over_y = np.clip(np.minimum(y + 1, cy + size / 2) - np.maximum(y, cy - size / 2), 0, 1)
    over_x = np.clip(np.minimum(x + 1, cx + size / 2) - np.maximum(x, cx - size / 2), 0, 1)
    return (over_y * over_x).astype(np.float32)


def _episode_arrays(rng: np.random.Generator, steps: int, heads: int) -> dict[str, np.ndarray]:
    keys = TOKENS.num_keys
    arrays: dict[str, np.ndarray] = {"step": np.arange(steps, dtype=np.int32), **TOKENS.to_arrays()}
    masks = {}
    for obs, (rows, cols) in (("image_primary", (16, 16)), ("image_wrist", (8, 8))):
        path = np.cumsum(rng.normal(0, 0.15, (steps, 2)), axis=0) + rng.uniform(3, rows - 3, 2)
        masks[f"{obs}/target"] = _box_fraction(steps, rows, cols, np.clip(path, 1, rows - 1), rng.uniform(1.5, 3.0))
        masks[f"{obs}/robot"] = _box_fraction(steps, rows, cols, np.clip(path[::-1] + 2, 1, rows - 1), rows / 3)
    logits = rng.standard_normal((steps, LAYERS, heads, READOUTS, keys), dtype=np.float32)
    focus = rng.uniform(0, 3, (1, LAYERS, heads, 1, 1)).astype(np.float32)  # some heads follow the target
    primary = camera_keys(TOKENS, "image_primary")
    logits[..., primary] += focus * masks["image_primary/target"].reshape(steps, 1, 1, 1, -1)
    np.exp(logits, out=logits)
    logits /= logits.sum(axis=-1, keepdims=True)
    arrays["readout_attention"] = logits.astype(np.float16)
    for name, frac in masks.items():
        arrays[f"mask_fraction/{name}"] = frac
        arrays[f"metrics/mask_area/{name}"] = frac.mean(axis=(1, 2))
        arrays[f"metrics/mask_mass/{name}"] = rng.random((steps, LAYERS), dtype=np.float32)
    for name in ("share/primary", "share/wrist", "share/language", "share/readout", "timestep_share/prefix",
                 "timestep_share/earlier", "timestep_share/current", "entropy"):
        arrays[f"metrics/{name}"] = rng.random((steps, LAYERS), dtype=np.float32)
    return arrays


def _template_video(path: Path, steps: int) -> None:
    """A real MP4 in the writers' frame layout (camera | overlay | captions over the per-layer strip)."""
    rng = np.random.default_rng(0)
    base = np.full((256, 256, 3), 200, np.uint8)
    base[160:256] = (150, 120, 90)
    writer = Mp4Writer(path, fps=10)
    for t in range(steps):
        frame = base.copy()
        x = 60 + (t % 120)
        frame[120:150, x:x + 30] = (200, 30, 30)
        maps = rng.random((LAYERS, 16, 16)).astype(np.float32)
        overlay = heatmap_overlay(frame, maps[-1])
        writer.append(video_frame(frame, overlay, maps, [f"step {t}"]))
    writer.close()


def generate(root: Path, tasks: int, episodes: int, steps: int, heads: int, measures: bool = True) -> Path:
    run = root / "bench-run"
    run.mkdir(parents=True)
    video = root / "template.mp4"
    _template_video(video, steps)
    names = [TASKS[i % len(TASKS)] + ("" if i < len(TASKS) else f"_{i}") for i in range(tasks)]
    jobs = [[task, k, k] for task in names for k in range(episodes)]
    manifest = {"format": "octo-harness-run/1", "run": run.name, "created": "2026-01-01T00:00:00+00:00",
                "protocol": {"model": "random:octo-small-1.5", "tasks": names, "episodes": episodes, "seed": 0,
                             "max_steps": steps, "execution": "temporal_ensemble"},
                "protocol_hash": "bench", "jobs": jobs,
                "model": {"source": "random:octo-small-1.5", "is_random": True, "note": "benchmark data",
                          "text_tokenizer": "t5-base", "dataset_key": None},
                "git_commit": None, "versions": {"numpy": np.__version__}}
    (run / "manifest.json").write_text(json.dumps(manifest))
    rng = np.random.default_rng(0)
    lines = []
    for task, k, seed in jobs:
        folder = run / task / f"episode_{k}"
        folder.mkdir(parents=True)
        arrays = _episode_arrays(rng, steps, heads)
        if measures:  # what the writers store at the end of an episode (runs made before that lack them)
            arrays.update(measure_arrays(arrays, TOKENS))
        np.savez(folder / "attention.npz", **arrays)
        np.savez(folder / "actions.npz", predicted=rng.random((steps, 4, 7), dtype=np.float32),
                 executed=rng.random((steps, 7), dtype=np.float32), step=arrays["step"])
        (folder / "metrics.jsonl").write_text("".join(json.dumps({"run": run.name, "task": task, "episode": k, "step": t})
                                                      + "\n" for t in range(steps)))
        os.link(video, folder / "rollout.mp4")
        success = bool(rng.random() < 0.4)
        (folder / "episode.json").write_text(json.dumps({"task": task, "episode": k, "seed": seed, "steps": steps,
                                                         "success": success, "options": {"video_camera": None}}))
        lines.append(json.dumps({"run": run.name, "task": task, "episode": k, "seed": seed, "status": "ok",
                                 "success": success, "steps": steps, "directory": f"{task}/episode_{k}", "error": None}))
    (run / "results.jsonl").write_text("\n".join(lines) + "\n")
    (run / "results.json").write_text(json.dumps({"status": "complete"}))
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", type=int, default=13)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--heads", type=int, default=12)
    parser.add_argument("--workers", type=int, default=None, help="report worker processes [report default]")
    parser.add_argument("--without-measures", action="store_true",
                        help="episodes as written before measures/* were stored: the report measures the attention")
    parser.add_argument("--keep", type=Path, default=None,
                        help="generate into this folder and keep it (a folder kept earlier is reused, not regenerated)")
    args = parser.parse_args()

    root = args.keep or Path(tempfile.mkdtemp(prefix="bench_report_"))
    try:
        start = time.perf_counter()
        if (root / "bench-run" / "results.json").is_file():  # --keep DIR from an earlier call: time the report again
            run = root / "bench-run"
        else:
            run = generate(root, args.tasks, args.episodes, args.steps, args.heads, not args.without_measures)
        generated = time.perf_counter() - start
        size = sum(p.stat().st_size for p in run.rglob("*.npz"))
        n = len(json.loads((run / "manifest.json").read_text())["jobs"])
        print(f"data: {args.tasks} tasks x {args.episodes} episodes x {args.steps} steps "
              f"({LAYERS} layers, {args.heads} heads, {TOKENS.num_keys} keys): {size / 1e9:.2f} GB of arrays in {generated:.0f} s")
        result = build_report([run], root / "report", ReportOptions(workers=args.workers))
        print(f"report: {result.seconds:.1f} s wall for {result.episodes} episodes ({result.episodes / result.seconds:.1f} "
              f"episodes/s), {len(result.plots)} plots; "
              f"target <= 60 s: {'met' if result.seconds <= 60 else 'MISSED'} ({result.seconds / 60:.2f} of the budget)")
        html = result.html.stat().st_size
        print(f"report.html {html / 1e6:.1f} MB; tables: " + ", ".join(
            f"{p.name} {p.stat().st_size / 1e6:.1f} MB" for p in sorted((result.out / "tables").iterdir())))
        assert result.episodes == n
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()

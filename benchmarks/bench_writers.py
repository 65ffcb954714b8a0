"""Per-step cost of the output writers at the released Octo layout (12 layers, 6 heads, 690 keys).

Prints milliseconds per control step for: attention metrics, PNG panels (rendering and encoding,
all 12 layers), the video frame (composition and MP4 encoding), and the whole background
EpisodeWriter (steps per second it sustains). Frames are synthetic scene-like images (smooth
shading, a few objects, sensor noise) at 256 px (primary) and 128 px (wrist).

    .venv/bin/python benchmarks/bench_writers.py [--steps 20]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from harness.measures.attention import camera_maps, step_metrics
from harness.octo.tokens import build_token_map
from harness.outputs.overlays import heatmap_overlay, layer_panel, video_frame
from harness.records import EpisodeMeta, StepRecord
from harness.outputs.video import Mp4Writer
from harness.outputs.panels import encode_png
from harness.outputs.writers import EpisodeWriter, OutputOptions

LAYERS, HEADS = 12, 6


def released_tokens():
    return build_token_map(
        [("task_language", 16)],
        [("obs_primary", 256), ("obs_wrist", 64), ("obs_task_language", 16), ("readout_action", 1)],
        2,
        (("obs_primary", "image_primary", 16, 16), ("obs_wrist", "image_wrist", 8, 8)),
    )


def scene(size: int, rng: np.random.Generator) -> np.ndarray:
    """(size, size, 3) uint8: shaded table, two boxes, mild noise (compresses a little worse than a render)."""
    y, x = np.mgrid[0:size, 0:size] / size
    img = np.stack([0.5 + 0.3 * y, 0.45 + 0.2 * x, 0.35 + 0.1 * (x + y)], -1)
    for _ in range(2):
        y0, x0 = rng.integers(0, size * 3 // 4, 2)
        img[y0 : y0 + size // 8, x0 : x0 + size // 8] = rng.random(3)
    img += rng.normal(0, 0.01, img.shape)
    return np.clip(img * 255, 0, 255).astype(np.uint8)


def records(n: int, tokens, rng) -> list[StepRecord]:
    target = np.zeros((256, 256), bool)
    target[120:150, 100:140] = True
    return [
        StepRecord(
            step=t,
            frames={"image_primary": scene(256, rng), "image_wrist": scene(128, rng)},
            readout_attention=rng.dirichlet(np.full(tokens.num_keys, 0.3), size=(LAYERS, HEADS, 1)).astype(np.float32),
            actions_predicted=rng.normal(size=(4, 7)).astype(np.float32),
            action_executed=rng.normal(size=7).astype(np.float32),
            reward=0.0,
            success=False,
            masks={"image_primary": {"target": target}},
        )
        for t in range(n)
    ]


def python_loop_seconds(repeats: int) -> float:
    """Median time of a fixed pure-Python loop (holds the GIL): slows down when another thread holds it."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sum(i * i for i in range(200_000))
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def ms(seconds: float, n: int) -> str:
    return f"{1000 * seconds / n:8.1f} ms"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args()
    n = args.steps
    rng = np.random.default_rng(0)
    tokens = released_tokens()
    recs = records(n, tokens, rng)
    print(f"layout: {LAYERS} layers x {HEADS} heads, {tokens.num_keys} keys, frames 256 + 128 px; {n} steps")

    t = time.perf_counter()
    for r in recs:
        step_metrics(r.readout_attention, tokens, r.masks)
    print(f"attention metrics per step           {ms(time.perf_counter() - t, n)}")

    render = encode = 0.0
    size = 0
    for r in recs:
        maps = {cam: camera_maps(r.readout_attention, tokens, cam).mean(axis=2) for cam in r.frames}
        for layer in range(LAYERS):
            t0 = time.perf_counter()
            panel = layer_panel(r.frames, {c: m[layer] for c, m in maps.items()}, {"task": "Lift", "step": r.step, "layer": layer})
            t1 = time.perf_counter()
            size += len(encode_png(panel, OutputOptions().png_compress_level))
            encode += time.perf_counter() - t1
            render += t1 - t0
    print(f"PNG panels per step, render (12)     {ms(render, n)}")
    print(f"PNG panels per step, encode (12)     {ms(encode, n)}   ({size / n / 12 / 1e3:.0f} kB per PNG, {panel.shape[1]}x{panel.shape[0]})")
    print(f"PNG panels per step, total           {ms(render + encode, n)}")

    with tempfile.TemporaryDirectory() as tmp:
        compose = append = 0.0
        writer = Mp4Writer(Path(tmp) / "bench.mp4", fps=10)
        for r in recs:
            t0 = time.perf_counter()
            maps = camera_maps(r.readout_attention, tokens, "image_primary").mean(axis=(1, 2))  # (layers, 16, 16)
            frame = r.frames["image_primary"]
            vf = video_frame(frame, heatmap_overlay(frame, maps[-1]), maps, ["Lift | step 0", "action: +0.1 +0.2"])
            t1 = time.perf_counter()
            writer.append(vf)
            append += time.perf_counter() - t1
            compose += t1 - t0
        t0 = time.perf_counter()
        writer.close()
        close = time.perf_counter() - t0
        print(f"video frame per step, compose        {ms(compose, n)}   ({vf.shape[1]}x{vf.shape[0]})")
        print(f"video frame per step, MP4 append     {ms(append, n)}   (+ {1000 * close:.0f} ms at close)")

        print(f"main-thread Python loop alone         {1000 * python_loop_seconds(9):8.1f} ms (probe for the GIL test below)")
        meta = EpisodeMeta("bench", "Lift", 0, 0, "lift the cube", "random:octo-small-1.5", True, None, "fallback", "temporal_ensemble")
        for label, opts in [
            ("all layers, every step", OutputOptions()),
            ("last layer only", OutputOptions(layers=(-1,))),
            ("video only", OutputOptions(png_every=0)),
        ]:
            t0 = time.perf_counter()
            opts = dataclasses.replace(opts, queue_size=n)  # enqueue everything, then probe the main thread
            ep = EpisodeWriter(Path(tmp) / label.replace(" ", "_").replace(",", ""), tokens, meta, opts)
            for r in recs:
                ep.add_step(r)
            busy = [python_loop_seconds(1) for _ in range(5)]  # while the writer works on the queued steps
            summary = ep.finish()
            total = time.perf_counter() - t0
            blocked = sum(ep.blocked_seconds)
            print(f"EpisodeWriter {label:<24s} {ms(total, n)} per step in the background "
                  f"(write {1000 * summary['timings']['mean']['write']:.1f} ms, finish {1000 * summary['timings']['finish']:.0f} ms,"
                  f" caller blocked {ms(blocked, n).strip()} per step when fed as fast as possible;"
                  f" main-thread loop meanwhile {1000 * statistics.median(busy):.1f} ms)")


if __name__ == "__main__":
    main()

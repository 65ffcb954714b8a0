"""Environment throughput: control steps per second with and without cameras, masks and fast rendering.

Each row makes one environment, resets it, warms up for a few steps and then times `--steps` control
steps (20 Hz robosuite control, 25 physics substeps each) with a small constant action. Cameras are
the defaults (agentview 256 px + eye-in-hand 128 px) unless the row says otherwise; "masks" adds one
segmentation render per camera; "fast" turns off shadows, reflections and the skybox.

    .venv/bin/python benchmarks/bench_envs.py [--task Lift] [--steps 40]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import envs

SMALL = {"image_primary": ("agentview", 64), "image_wrist": ("robot0_eye_in_hand", 32)}
ROWS = (
    ("no cameras (physics only)", dict(cameras={})),
    ("cameras 256+128", dict()),
    ("cameras 256+128, masks", dict(masks=True)),
    ("cameras 256+128, fast", dict(fast_render=True)),
    ("cameras 256+128, fast, masks", dict(fast_render=True, masks=True)),
    ("cameras 64+32", dict(cameras=SMALL)),
    ("cameras 64+32, masks", dict(cameras=SMALL, masks=True)),
)


def time_steps(task: str, steps: int, options: dict) -> tuple[float, float]:
    """(steps per second, reset seconds) for one environment configuration."""
    env = envs.make(task, **options)
    try:
        start = time.perf_counter()
        env.reset(seed=0)
        reset_seconds = time.perf_counter() - start
        action = np.array([0.002, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], dtype=np.float32)
        for _ in range(3):
            env.step(action)
        start = time.perf_counter()
        for _ in range(steps):
            env.step(action)
        return steps / (time.perf_counter() - start), reset_seconds
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--task", default="Lift")
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()

    results = [(name, *time_steps(args.task, args.steps, options)) for name, options in ROWS]
    physics = results[0][1]
    print(f"task {args.task}, {args.steps} timed steps per row")
    print(f"{'configuration':32s} {'steps/s':>9s} {'ms/step':>9s} {'vs physics':>11s} {'reset s':>8s}")
    for name, rate, reset_seconds in results:
        print(f"{name:32s} {rate:9.1f} {1000 / rate:9.1f} {physics / rate:10.1f}x {reset_seconds:8.3f}")
    default, masks, fast = results[1][1], results[2][1], results[3][1]
    print(f"mask overhead at 256+128: {default / masks - 1:+.0%} per step; fast render speed-up: {fast / default:.2f}x")


if __name__ == "__main__":
    main()

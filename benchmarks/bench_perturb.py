"""Cost of perturbations: s/step and reset time per kind against the nominal scene, and the protocol hash.

Each row makes one environment (default cameras 256 + 128 px, masks, fast render as a grid runs), times `--resets`
resets with different seeds (the reset-time modding: camera, lighting, texture, distractor placement, init-state)
and `--steps` control steps with a small constant action (per-step cost: only sensor noise works per step).
Rows are interleaved over `--repeats` rounds and the median is reported, so load changes hit every row alike.
The first line checks that a protocol without perturbation and one with every kind at level 0 have the same hash.

    .venv/bin/python benchmarks/bench_perturb.py [--task Lift] [--steps 30] [--resets 5] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import envs
from envs.perturbations import KINDS
from harness.run.protocol import Protocol

ROWS = ("", "camera:5", "lighting:5", "texture:5", "distractors:5", "init-state:5", "noise:1", "noise:5", "language:5")


def measure(task: str, spec: str, steps: int, resets: int) -> tuple[float, float, float]:
    """(construction s, reset s (median), s/step (mean over `steps`)) of one environment."""
    start = time.perf_counter()
    env = envs.make(task, masks=True, fast_render=True, perturb=spec or None)
    built = time.perf_counter() - start
    try:
        reset_times = []
        for seed in range(resets):
            start = time.perf_counter()
            env.reset(seed=seed)
            reset_times.append(time.perf_counter() - start)
        action = np.array([0.002, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], dtype=np.float32)
        env.step(action)
        start = time.perf_counter()
        for _ in range(steps):
            env.step(action)
        return built, statistics.median(reset_times), (time.perf_counter() - start) / steps
    finally:
        env.close()


def noise_cost(level: int, repeats: int = 200) -> float:
    """Seconds per control step that sensor noise adds: noise_frame on a 256 px and a 128 px frame (the default
    cameras), timed alone (no simulator), so machine load from rendering does not blur it."""
    from envs.perturbations import noise_frame, parse_perturb

    (p,) = parse_perturb(f"noise:{level}")
    rng = np.random.default_rng(0)
    frames = {"image_primary": rng.integers(0, 256, (256, 256, 3), dtype=np.uint8),
              "image_wrist": rng.integers(0, 256, (128, 128, 3), dtype=np.uint8)}
    start = time.perf_counter()
    for step in range(repeats):
        for key, frame in frames.items():
            noise_frame(frame, 0, p, step, key)
    return (time.perf_counter() - start) / repeats


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--task", default="Lift")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--resets", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    plain = Protocol(model="random:octo-small-1.5", tasks=(args.task,))
    zero = plain.replace(perturb=",".join(f"{k}:0" for k in KINDS))
    print(f"protocol hash: no perturbation {plain.hash()[:16]}, every kind at level 0 {zero.hash()[:16]} "
          f"({'same' if plain.hash() == zero.hash() else 'DIFFERENT'})")
    rounds = {spec: [] for spec in ROWS}
    for _ in range(args.repeats):
        for spec in ROWS:
            rounds[spec].append(measure(args.task, spec, args.steps, args.resets))
    base = [statistics.median(r[i] for r in rounds[""]) for i in range(3)]
    print(f"task {args.task}, cameras 256+128 px, masks, fast render; median of {args.repeats} rounds")
    print(f"{'perturbation':16s} {'build s':>8s} {'reset s':>8s} {'reset +s':>9s} {'s/step':>8s} {'step +ms':>9s}")
    for spec in ROWS:
        built, reset, step = (statistics.median(r[i] for r in rounds[spec]) for i in range(3))
        print(f"{spec or 'none':16s} {built:8.2f} {reset:8.3f} {reset - base[1]:+9.3f} {step:8.4f} "
              f"{(step - base[2]) * 1e3:+9.1f}")
    for level in (1, 3, 5):
        print(f"sensor noise alone, level {level}: {noise_cost(level) * 1e3:.2f} ms per step (256 + 128 px frames)")


if __name__ == "__main__":
    main()

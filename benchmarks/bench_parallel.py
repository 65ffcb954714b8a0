"""Env-steps per second of the executors on the same episodes, and this machine's bound, measured in one run.

Rows: the sequential executor, `--workers 1, 2, 4` (env-worker processes, batched inference in the driver) and
Ray with 2 env-worker actors (+ 1 policy replica), each as a ratio to sequential. Every executor first runs one
short warm-up episode per worker (processes started, envs made, every batch size compiled), then the timed
episodes on the same executor: env-steps/s = steps of the timed episodes / their wall time. Outputs are off
(no PNG, no MP4; the attention metrics are still computed) so the numbers are simulation + inference + harness.

Bound: cores / (inference core-seconds + simulation core-seconds per step), with the core-seconds measured
here by process CPU time (time.process_time: all threads of the process: XLA's pool, llvmpipe's render
threads) around `policy.step` and `env.step` of a plain closed loop. No schedule can beat it: every step
needs that much CPU. Targets on a 2-core CPU: 2 workers >= 1.1x sequential and >= 85% of the bound.
Batching: the core-seconds per example of one batched inference call at batch 1 and 2 (what batching the
workers' requests can save per step; the bound assumes it saves nothing).

    .venv/bin/python benchmarks/bench_parallel.py [--model random:octo-small-1.5] [--episodes 4] [--steps 15]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def core_seconds_per_step(model, protocol, steps: int) -> dict:
    """Wall and CPU seconds per step of inference and of simulation in a plain closed loop (after one compile)."""
    import envs

    env = envs.make(protocol.tasks[0], protocol.env)
    policy = model.closed_loop(protocol.policy)
    totals = dict(inference_cpu=0.0, simulation_cpu=0.0, inference_wall=0.0, simulation_wall=0.0)
    try:
        obs, info = env.reset(seed=100)
        policy.reset(info["instruction"], seed=100)
        env.step(policy.step(obs).action)  # compiles outside the measurement
        for _ in range(steps):
            c0, w0 = time.process_time(), time.perf_counter()
            decision = policy.step(obs)
            c1, w1 = time.process_time(), time.perf_counter()
            obs, *_ = env.step(decision.action)
            c2, w2 = time.process_time(), time.perf_counter()
            totals["inference_cpu"] += c1 - c0
            totals["simulation_cpu"] += c2 - c1
            totals["inference_wall"] += w1 - w0
            totals["simulation_wall"] += w2 - w1
    finally:
        env.close()
    return {k: v / steps for k, v in totals.items()}


def batch_core_seconds(model, protocol, sizes=(1, 2), calls: int = 6) -> dict[int, float]:
    """Core-seconds per example of one batched inference call at each batch size (after compiling them)."""
    import numpy as np

    from harness.policy import TaskPrompt
    from harness.run.workers import PolicyShape, warmup_request

    out = {}
    for b in sizes:  # one inference per shape: a run compiles exactly its protocol's inference_batch
        inference = model.inference(dataclasses.replace(protocol.policy, inference_batch=b))
        request = warmup_request(PolicyShape.of(model, inference.dataset_key), TaskPrompt.of("pick up the red cube"))
        rng = np.random.default_rng(0)
        for value in request.observation.values():
            if isinstance(value, np.ndarray) and value.dtype == np.uint8:
                value[:] = rng.integers(0, 256, value.shape)
        inference.warm_up(request)
        c0 = time.process_time()
        for _ in range(calls):
            inference([request] * b)
        out[b] = (time.process_time() - c0) / calls / b
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--model", default="random:octo-small-1.5")
    parser.add_argument("--task", default="Lift")
    parser.add_argument("--episodes", type=int, default=4, help="timed episodes per executor")
    parser.add_argument("--steps", type=int, default=15, help="control steps per episode")
    parser.add_argument("--workers", default="1,2,4", help="local worker counts to measure")
    parser.add_argument("--ray-workers", type=int, default=2, help="Ray env-worker actors (0 = skip Ray)")
    args = parser.parse_args()

    import envs
    from harness.policies import load_policy
    from harness.run.executor import EpisodeContext, SequentialExecutor
    from harness.run.protocol import EpisodeJob, Protocol
    from harness.run.workers import WorkersExecutor
    from harness.outputs.writers import OutputOptions

    model = load_policy(args.model)
    protocol = Protocol(model=args.model, tasks=(args.task,), episodes=args.episodes, max_steps=args.steps,
                        env=envs.EnvOptions(masks=True), outputs=OutputOptions(png_every=0, video=False))
    cores = os.cpu_count() or 1
    cost = core_seconds_per_step(model, protocol, steps=max(10, args.steps))
    bound = cores / (cost["inference_cpu"] + cost["simulation_cpu"])
    per_example = batch_core_seconds(model, protocol)

    executors: list[tuple[str, object]] = [("sequential", SequentialExecutor)]
    executors += [(f"--workers {n}", functools.partial(WorkersExecutor, workers=int(n))) for n in args.workers.split(",")]
    if args.ray_workers:
        from harness.run.ray_executor import RayExecutor

        executors.append((f"ray, {args.ray_workers} workers", functools.partial(RayExecutor, workers=args.ray_workers)))

    results = []
    with tempfile.TemporaryDirectory() as out:
        for label, factory in executors:
            run_dir = Path(out) / label.replace(" ", "_").replace(",", "")
            context = EpisodeContext(protocol=protocol, run_dir=str(run_dir), run=run_dir.name,
                                     model={"source": model.source, "is_random": model.is_random, "dataset_key": None},
                                     goals=None)
            executor = factory(context, model)
            n_workers = getattr(executor, "workers", 1)
            warm = [EpisodeJob(args.task, 1000 + i, 1000 + i) for i in range(n_workers)]
            jobs = [EpisodeJob(args.task, k, k) for k in range(args.episodes)]
            try:
                list(executor.run(warm))
                start = time.perf_counter()
                rows = list(executor.run(jobs))
                wall = time.perf_counter() - start
            finally:
                executor.close()
            failed = [r for r in rows if r.status != "ok"]
            if failed:
                raise SystemExit(f"{label}: {len(failed)} episodes failed: {failed[0].error}")
            steps = sum(r.steps for r in rows)
            results.append((label, steps / wall, wall, steps))
            pool = getattr(executor, "pool", None)
            served = (f"; inference calls of 1/2/..: {[pool.batches.count(b) for b in range(1, pool.max_batch + 1)]}"
                      if pool is not None else "")
            print(f"{label:<20} {steps / wall:6.2f} env-steps/s ({steps} steps in {wall:.1f} s{served})", flush=True)

    seq = results[0][1]
    print(f"\nmodel {args.model}, task {args.task}, cameras 256+128 px, masks on, no PNG/MP4; {args.episodes} episodes x "
          f"{args.steps} steps per executor, after warm-up; {cores} cores")
    print(f"per step: inference {cost['inference_cpu']:.3f} core-s ({cost['inference_wall']:.3f} s wall), simulation "
          f"{cost['simulation_cpu']:.3f} core-s ({cost['simulation_wall']:.3f} s wall)")
    print(f"batched inference, core-s per example: batch 1 {per_example[1]:.3f}, batch 2 {per_example[2]:.3f} "
          f"({per_example[2] / per_example[1]:.2f}x: what batching saves per step)")
    print(f"bound: {cores} cores / {cost['inference_cpu'] + cost['simulation_cpu']:.3f} core-s per step = {bound:.2f} env-steps/s\n")
    print("| executor | env-steps/s | vs sequential | of bound |\n|---|---:|---:|---:|")
    for label, rate, _, _ in results:
        print(f"| {label} | {rate:.2f} | {rate / seq:.2f}x | {rate / bound:.0%} |")
    print("\ntargets (2-core CPU): --workers 2 >= 1.1x sequential and >= 85% of the bound")
    import jax

    if jax.default_backend() != "gpu":
        print("no GPU here: the GPU target (octo-small-1.5, 16 workers >= 40 env-steps/s, GPU busy >= 50%) is not measured")


if __name__ == "__main__":
    main()

"""The policy's batched inference (harness.policies.octo.BatchInference, what --workers and --inference-batch use): wall
time per call and per example at each --inference-batch size, through the whole policy path (observation
windows, proprio normalisation, per-example rng keys, padding to the fixed batch, unnormalisation).

A full call carries `batch` requests (as when `batch` workers wait); per example = call / batch. On a CPU one
inference already uses every core, so the per-example cost hardly falls; on a GPU it falls steeply, which is
when a larger --inference-batch pays.

    .venv/bin/python benchmarks/bench_inference_batch.py [--models models/octo-reference-robosuite,random:octo-base-1.5]
                                                         [--batches 1,2,4,8,16] [--reps 7]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import jax  # noqa: E402
import numpy as np  # noqa: E402

from harness.policies import load_policy  # noqa: E402
from harness.policy import InferenceRequest, PolicyConfig, TaskPrompt  # noqa: E402


def request(model, seed: int) -> InferenceRequest:
    """A random observation window of the model's sizes (one episode's input, no batch axis)."""
    rng = np.random.default_rng(seed)
    window = model.window_size
    obs: dict = {k: rng.integers(0, 256, (window, h, w, 3), dtype=np.uint8) for k, (h, w) in model.image_sizes.items()}
    lowdim = dict(getattr(model, "lowdim_sizes", None) or {})
    obs.update({k: rng.normal(size=(window, n)).astype(np.float32) for k, n in lowdim.items()})
    obs["timestep_pad_mask"] = np.ones((window,), bool)
    obs["pad_mask_dict"] = {k: np.ones((window,), bool) for k in [*model.image_sizes, *lowdim]}
    return InferenceRequest(observation=obs, task=TaskPrompt.of("pick up the red cube"), seed=seed, step=0)


def bench(source: str, batches: list[int], reps: int) -> list[tuple[str, int, float]]:
    model = load_policy(source)
    rows = []
    for batch in batches:
        inference = model.inference(PolicyConfig(inference_batch=batch))
        requests = [request(model, seed) for seed in range(batch)]
        inference.warm_up(requests[0])
        inference(requests)
        times = []
        for _ in range(reps):
            start = time.perf_counter()
            inference(requests)
            times.append(time.perf_counter() - start)
        rows.append((source, batch, statistics.median(times)))
        print(f"  {source} batch {batch}: done", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--models", default="models/octo-reference-robosuite,random:octo-small-1.5")
    parser.add_argument("--batches", default="1,2,4,8")
    parser.add_argument("--reps", type=int, default=7)
    args = parser.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    print(f"jax {jax.__version__} on {jax.devices()[0].platform} ({jax.devices()[0].device_kind}), {os.cpu_count()} CPUs",
          flush=True)
    rows = [row for source in args.models.split(",") for row in bench(source, batches, args.reps)]
    print(f"\n{'model':<36} {'batch':>5} {'ms/call':>9} {'ms/example':>11} {'vs batch 1':>11}")
    first = {}
    for source, batch, seconds in rows:
        per = seconds / batch
        first.setdefault(source, per)
        print(f"{source:<36} {batch:>5} {seconds * 1e3:>9.1f} {per * 1e3:>11.2f} {first[source] / per:>10.2f}x")


if __name__ == "__main__":
    main()

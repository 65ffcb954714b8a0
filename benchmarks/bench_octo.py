"""Octo runtime speed: sample_actions latency with attention capture off / readout rows / full matrices,
the capture overhead as a ratio, and the transformer's achieved GFLOP/s as a fraction of a large float32
matmul's GFLOP/s measured in the same run.

Real input sizes: window 2, 256 px primary, 128 px wrist, 16 language tokens; batch 1 and 4; the
octo-small-1.5 and octo-base-1.5 architectures (random weights: same shapes, same FLOPs).
Targets: readout capture overhead <= 5%; transformer >= 60% of the matmul rate.

    .venv/bin/python benchmarks/bench_octo.py [--archs octo-small-1.5,octo-base-1.5] [--batches 1,4] [--reps 7]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from harness.policies import load_policy  # noqa: E402
from harness.octo.transformer import Transformer  # noqa: E402

MODES = {  # label -> sample_actions keyword arguments
    "off": {"capture_attention": False},
    "readout": {},
    "full": {"full_attention": True},
}


def median_seconds(fn, reps: int) -> float:
    """Median wall time of `fn()` (which must block until its result is ready) after one warm-up call."""
    fn()
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def interleaved_medians(calls: dict, reps: int) -> dict[str, float]:
    """Median wall time per labelled call, timing the calls round-robin so machine-load drift hits all alike."""
    for fn in calls.values():  # compile + warm up
        fn()
    times: dict[str, list[float]] = {label: [] for label in calls}
    for _ in range(reps):
        for label, fn in calls.items():
            start = time.perf_counter()
            fn()
            times[label].append(time.perf_counter() - start)
    return {label: statistics.median(t) for label, t in times.items()}


def matmul_gflops(n: int = 2048, reps: int = 10) -> float:
    """GFLOP/s of a jitted (n, n) @ (n, n) float32 matmul."""
    a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jnp.float32)
    b = jax.random.normal(jax.random.PRNGKey(1), (n, n), jnp.float32)
    f = jax.jit(jnp.matmul)
    seconds = median_seconds(lambda: f(a, b).block_until_ready(), reps)
    return 2 * n**3 / seconds / 1e9


def transformer_flops(batch: int, tokens: int, dim: int, mlp: int, layers: int) -> float:
    """Multiply-add FLOPs (x2) of the encoder stack: q/k/v/out projections, scores, weighted sum, MLP."""
    per_layer = 2 * tokens * dim * 4 * dim + 2 * 2 * tokens * tokens * dim + 2 * 2 * tokens * dim * mlp
    return batch * layers * per_layer


def observations(model, batch: int, rng: np.random.Generator) -> dict:
    window = model.window_size
    obs = {
        key: rng.integers(0, 256, (batch, window, h, w, 3), dtype=np.uint8) for key, (h, w) in model.image_sizes.items()
    }
    obs["timestep_pad_mask"] = np.ones((batch, window), bool)
    return obs


def bench_arch(arch: str, batches: list[int], reps: int) -> list[dict]:
    model = load_policy(f"random:{arch}").model  # the Octo model itself: this benchmark times its parts
    cfg = model.config
    rows = []
    for batch in batches:
        rng = np.random.default_rng(0)
        obs = observations(model, batch, rng)
        task = model.create_task(texts=["pick up the red cube"] * batch)
        key = jax.random.PRNGKey(0)
        row = {"arch": arch, "batch": batch}
        calls = {}
        for label, kwargs in MODES.items():

            def call(kwargs=kwargs):
                actions, attention = model.sample_actions(obs, task, key, **kwargs)
                jax.block_until_ready((actions, None if attention is None else (attention.readout, attention.full)))

            calls[label] = call
        row.update(interleaved_medians(calls, reps))
        tokens = model.token_map().num_keys
        dim = cfg.token_embedding_size
        layer_cfg = cfg.transformer
        x = jax.random.normal(jax.random.PRNGKey(2), (batch, tokens, dim), jnp.float32)
        mask = jnp.ones((batch, 1, tokens, tokens), bool)
        params = model.params["octo_transformer"]["BlockTransformer_0"]["Transformer_0"]
        stack = Transformer(layer_cfg, capture_rows=())
        f = jax.jit(lambda p, x, m: stack.apply({"params": p}, x, m)[0])
        row["transformer"] = median_seconds(lambda: f(params, x, mask).block_until_ready(), reps)
        row["tokens"] = tokens
        row["gflop"] = transformer_flops(batch, tokens, dim, layer_cfg.mlp_dim, layer_cfg.num_layers) / 1e9
        rows.append(row)
        print(f"  {arch} batch {batch}: done", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--archs", default="octo-small-1.5,octo-base-1.5")
    parser.add_argument("--batches", default="1,4")
    parser.add_argument("--reps", type=int, default=5)
    args = parser.parse_args()
    batches = [int(b) for b in args.batches.split(",")]

    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPUs; float32", flush=True)
    rows = []
    for arch in args.archs.split(","):
        rows += bench_arch(arch, batches, args.reps)
    peak = matmul_gflops()

    print("\nsample_actions median latency (ms) by attention capture, and overhead vs capture off")
    print(f"{'model':<16} {'batch':>5} {'off':>8} {'readout':>8} {'full':>8} {'readout ovh':>12} {'full ovh':>9}")
    for r in rows:
        print(f"{r['arch']:<16} {r['batch']:>5} {r['off'] * 1e3:>8.1f} {r['readout'] * 1e3:>8.1f} {r['full'] * 1e3:>8.1f} "
              f"{r['readout'] / r['off'] - 1:>12.1%} {r['full'] / r['off'] - 1:>9.1%}")
    print(f"\ntransformer stack alone ({rows[0]['tokens']} tokens) vs a 2048^3 float32 matmul at {peak:.1f} GFLOP/s")
    print(f"{'model':<16} {'batch':>5} {'ms':>8} {'GFLOP':>8} {'GFLOP/s':>8} {'of matmul':>10}")
    for r in rows:
        rate = r["gflop"] / r["transformer"]
        print(f"{r['arch']:<16} {r['batch']:>5} {r['transformer'] * 1e3:>8.1f} {r['gflop']:>8.1f} {rate:>8.1f} "
              f"{rate / peak:>10.0%}")
    print("\ntargets: readout capture overhead <= 5%; transformer >= 60% of the matmul rate")


if __name__ == "__main__":
    main()

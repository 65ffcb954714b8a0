"""What attribution and open-loop faithfulness cost per control step (harness/measures/attribution.Probe).

For each model: the policy's own inference (the policy's inference, batch 1, as a run calls it), the attribution maps
alone (what `--attribution` adds at every inference step: one forward + one backward), and one faithfulness
step (maps + deletion/insertion curves of every method and camera). The added time per step with
`--faithfulness-every k` is maps + faithfulness/k (plus maps at every step when --attribution is on; a
faithfulness run computes maps at every step, as the run stores them). Ratios are to the policy's inference
and to a whole closed-loop step (inference + `--sim` seconds of simulation, default 0.03 s: a --fast-render
Lift step, README).

With --fills mean,blur,impute, one faithfulness step is timed per fill (same maps, same inputs, measured in one
process, alternating fills rep by rep so load drifts hit them alike) and each fill's cost is given relative to
mean fill's (the issue's target for impute: within 1.5x of mean).

    .venv/bin/python benchmarks/bench_faithfulness.py [--models models/octo-reference-robosuite,random:octo-small-1.5]
        [--methods-small attention:-1,saliency] [--every 10] [--reps 5] [--fills mean,blur,impute]

Nothing changes when faithfulness is off: the inference builds no probe without --attribution or
--faithfulness-every (the same code path as before), so a plain run's s/step is unchanged.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402

from bench_octo import median_seconds  # noqa: E402  (one timing rule for the benchmarks)
from harness.policies import load_policy  # noqa: E402
from harness.policy import InferenceRequest, PolicyConfig, TaskPrompt  # noqa: E402


def request(model) -> InferenceRequest:
    rng = np.random.default_rng(0)
    window = model.window_size
    obs = {k: rng.integers(0, 255, (window, h, w, 3), dtype=np.uint8) for k, (h, w) in model.image_sizes.items()}
    for key, dims in model.lowdim_sizes.items():
        obs[key] = rng.standard_normal((window, dims)).astype(np.float32)
    keys = [*model.image_sizes, *model.lowdim_sizes]
    obs["timestep_pad_mask"] = np.ones((window,), bool)
    obs["pad_mask_dict"] = {k: np.ones((window,), bool) for k in keys}
    return InferenceRequest(obs, TaskPrompt.of("pick up the red cube"), 0, 0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="models/octo-reference-robosuite,random:octo-small-1.5")
    parser.add_argument("--methods", default="attention,rollout,grad-attention,saliency",
                        help="attribution methods for small models (12 or fewer patches per side)")
    parser.add_argument("--methods-large", default="attention:-1,saliency",
                        help="methods for models with large patch grids (octo-small: 16x16 + 8x8 patches)")
    parser.add_argument("--every", type=int, default=10)
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--sim", type=float, default=0.03, help="seconds of simulation per step (fast render)")
    parser.add_argument("--fills", default=None,
                        help="time one faithfulness step per fill instead (e.g. mean,blur,impute) and compare with mean")
    args = parser.parse_args()
    if args.fills:
        return compare_fills(args)
    print(f"{'model':<36} {'methods':<44} {'infer s':>8} {'maps s':>8} {'faith s':>8} "
          f"{'added/step s':>12} {'x infer':>8} {'x step':>7}")
    for source in args.models.split(","):
        model = load_policy(source)
        large = max(h for h, _ in model.image_sizes.values()) > 128
        methods = args.methods_large if large else args.methods
        req = request(model)
        key = None if model.is_random else "robosuite_reference" if "robosuite_reference" in model.dataset_statistics else None
        plain = model.inference(PolicyConfig(dataset_key=key))
        probed = model.inference(PolicyConfig(dataset_key=key, attribution=methods, faithfulness_every=args.every))
        infer = median_seconds(lambda: plain([req]), args.reps)
        observations, tasks, keys = probed._inputs([req])
        maps = median_seconds(lambda: probed.probe("attribution").maps(observations, tasks, keys[0], 0, 1), args.reps)  # step 1: maps only
        faith = median_seconds(lambda: probed.probe("attribution").maps(observations, tasks, keys[0], 0, 0), max(1, args.reps // 3 if large else args.reps))
        added = maps + (faith - maps) / args.every
        print(f"{source:<36} {methods:<44} {infer:8.3f} {maps:8.3f} {faith:8.2f} {added:12.3f} "
              f"{added / infer:8.2f} {added / (infer + args.sim):7.2f}")


def compare_fills(args) -> None:
    """One faithfulness step per fill, reps alternating between fills; medians and ratios to mean fill."""
    import time

    from harness.measures.attribution import Probe

    fills = [f.strip() for f in args.fills.split(",") if f.strip()]
    print(f"{'model':<36} {'methods':<44} " + " ".join(f"{f + ' s':>9}" for f in fills)
          + " " + " ".join(f"{f + '/mean':>12}" for f in fills if f != "mean"))
    for source in args.models.split(","):
        model = load_policy(source)
        large = max(h for h, _ in model.image_sizes.values()) > 128
        methods = args.methods_large if large else args.methods
        req = request(model)
        key = None if model.is_random else "robosuite_reference" if "robosuite_reference" in model.dataset_statistics else None
        probed = model.inference(PolicyConfig(dataset_key=key, attribution=methods, faithfulness_every=1))
        observations, tasks, keys = probed._inputs([req])
        probes = {f: Probe(model, methods, 1, f) for f in fills}
        for f in fills:  # compile
            probes[f](observations, tasks, keys[0], 0, 0)
        times = {f: [] for f in fills}
        for _ in range(args.reps):
            for f in fills:
                start = time.perf_counter()
                probes[f](observations, tasks, keys[0], 0, 0)
                times[f].append(time.perf_counter() - start)
        med = {f: float(np.median(times[f])) for f in fills}
        print(f"{source:<36} {methods:<44} " + " ".join(f"{med[f]:9.2f}" for f in fills) + " "
              + " ".join(f"{med[f] / med['mean']:12.2f}" for f in fills if f != "mean" and "mean" in med))


if __name__ == "__main__":
    main()

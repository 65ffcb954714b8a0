"""Per-control-step time split of a closed-loop rollout: simulation, inference, enqueue, and the harness's overhead.

Runs one real episode (robosuite Lift, real JAX model) with writing in the background and prints the mean
seconds per step of each part and the overhead fraction (total - simulation - inference) / total.
Target: overhead <= 10% of the step with writing in the background.

    .venv/bin/python benchmarks/bench_rollout.py [--model random:octo-small-1.5] [--steps 30]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--model", default="random:octo-small-1.5")
    parser.add_argument("--task", default="Lift")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--png-every", type=int, default=1)
    args = parser.parse_args()

    from harness.policies import load_policy
    from harness.policy import PolicyConfig
    from harness.run import Protocol, execute
    from harness.outputs.writers import OutputOptions

    model = load_policy(args.model)
    rows = []
    with tempfile.TemporaryDirectory() as out:
        # warm-up: compiles sample_actions so the measured episodes show steady-state steps
        execute(Protocol(model=model.source, tasks=(args.task,), max_steps=2), out, "warmup", model=model,
                progress=False)
        for label, outputs in [
            ("png every step + mp4", OutputOptions(png_every=args.png_every)),
            ("mp4 only", OutputOptions(png_every=0)),
            ("no png, no mp4", OutputOptions(png_every=0, video=False)),
        ]:
            protocol = Protocol(model=model.source, tasks=(args.task,), episodes=1, max_steps=args.steps,
                                policy=PolicyConfig(), outputs=outputs)
            start = time.perf_counter()
            summary = execute(protocol, out, label.replace(" ", "_").replace("+", ""), model=model, progress=False)
            wall = time.perf_counter() - start
            r = summary.rows[0]
            rows.append((label, r, wall))

    print(f"\nmodel {args.model}, task {args.task}, {args.steps} steps, after a warm-up episode (compiled)")
    print(f"{'outputs':<24} {'s/step':>7} {'sim':>7} {'infer':>7} {'overhead':>9} {'episode wall s':>15}")
    for label, r, wall in rows:
        print(f"{label:<24} {r.seconds_per_step:>7.3f} {r.simulation_per_step:>7.3f} {r.inference_per_step:>7.3f} "
              f"{r.overhead_fraction:>9.1%} {wall:>15.1f}")
    print("target: overhead <= 10% of the step (writing in the background)")
    print("background writing shares the CPU: compare s/step with the 'no png, no mp4' row for its full cost")


if __name__ == "__main__":
    main()

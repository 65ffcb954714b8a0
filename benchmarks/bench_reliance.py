"""What region reliance costs per control step (harness/probes/reliance/measure.py, issue 45): a policy with a reliance
interval (default 4) against the same policy with none, on the same recorded closed-loop inputs, in one process.

A Lift episode of the model is recorded first (its observations and the env's masks, `--steps` steps, with its
checkpoint's conventions: the reference policy reads agentview 256 px at 128 px and the wrist 128 px at 64 px);
then both policies step through those inputs as a fresh episode each, alternating rep by rep so load drifts hit
them alike. Per step: policy seconds off and on (median over reps of the episode's mean); the overhead ratio on /
off of the policy alone and of a whole closed-loop step (plus the median simulation step of the recording). Each
sampled step costs one batched call of 1 + sum over cameras (regions with pixels + 1) forward passes.

    .venv/bin/python benchmarks/bench_reliance.py [--model models/octo-reference-robosuite] [--every 4]
        [--steps 8] [--reps 5] [--fill impute] [--task Lift] [--save-inputs FILE | --inputs FILE]

`--save-inputs` keeps the recording; `--inputs` replays it on a machine without the simulator (the GPU figure).

Off is the code path without reliance: the inference builds no RelianceProbe and no request carries masks.
"""

from __future__ import annotations

import argparse
import os
import pickle
import statistics
import time

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

from harness.conventions import CheckpointConventions  # noqa: E402
from harness.policies import load_policy  # noqa: E402
from harness.policy import ClosedLoopPolicy  # noqa: E402


def record(env, policy: ClosedLoopPolicy, steps: int, seed: int = 0) -> tuple[list, str, float]:
    """([(observation, masks)] of `steps` closed-loop steps, the instruction, median simulation seconds per step)."""
    obs, info = env.reset(seed=seed)
    policy.reset(info["instruction"], seed=seed)
    inputs, sim = [], []
    for _ in range(steps):
        inputs.append((obs, info["masks"]))
        action = policy.step(obs, info["masks"]).action
        start = time.perf_counter()
        obs, _, terminated, truncated, info = env.step(action)
        sim.append(time.perf_counter() - start)
        if terminated or truncated:
            break
    return inputs, info.get("instruction", ""), statistics.median(sim)


def episode_seconds(policy: ClosedLoopPolicy, inputs: list, instruction: str, seed: int = 0) -> float:
    """Mean policy seconds per step over the recorded inputs, as a fresh episode."""
    policy.reset(instruction, seed=seed)
    start = time.perf_counter()
    for obs, masks in inputs:
        policy.step(obs, masks)
    return (time.perf_counter() - start) / len(inputs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="models/octo-reference-robosuite")
    parser.add_argument("--task", default="Lift")
    parser.add_argument("--every", type=int, default=4)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--fill", default="impute")
    parser.add_argument("--save-inputs", metavar="FILE", help="also save the recorded inputs (pickle) for --inputs")
    parser.add_argument("--inputs", metavar="FILE", help="read the inputs --save-inputs saved instead of simulating "
                        "(a machine without the simulator, e.g. a GPU box)")
    args = parser.parse_args()
    model = load_policy(args.model)
    conventions = CheckpointConventions.read(args.model if os.path.isdir(args.model) else None)
    off = model.closed_loop(conventions.policy_config())
    on = model.closed_loop(conventions.policy_config({"reliance_every": args.every, "reliance_fill": args.fill}))
    if args.inputs:
        with open(args.inputs, "rb") as f:
            inputs, instruction, sim = pickle.load(f)
    else:
        import envs

        env = envs.make(args.task, conventions.env_options({"masks": True, "fast_render": True}))
        try:
            inputs, instruction, sim = record(env, off, args.steps)
        finally:
            env.close()
    if args.save_inputs:
        with open(args.save_inputs, "wb") as f:
            pickle.dump((inputs, instruction, sim), f)
    policies = {"off": off, "on": on}
    for policy in policies.values():  # compile and warm up
        episode_seconds(policy, inputs, instruction)
    times = {label: [] for label in policies}
    for _ in range(args.reps):
        for label, policy in policies.items():
            times[label].append(episode_seconds(policy, inputs, instruction))
    med = {label: statistics.median(t) for label, t in times.items()}
    sampled = sum(1 for t in range(len(inputs)) if t % args.every == 0)
    on.reset(instruction, seed=0)
    rows = on.step(*inputs[0]).probes["reliance"]["rows"]
    passes = 1 + len({r["camera"] for r in rows}) + sum(1 for r in rows if r["area_fraction"] > 0)
    print(f"model {args.model}, task {args.task}, {len(inputs)} steps ({sampled} sampled, every {args.every}), "
          f"fill {args.fill}, {passes} forward passes per sampled step (step 0), {args.reps} reps")
    print(f"{'policy off s/step':>18} {'policy on s/step':>17} {'sim s/step':>11} {'x policy':>9} {'x closed-loop step':>19}")
    print(f"{med['off']:18.4f} {med['on']:17.4f} {sim:11.4f} {med['on'] / med['off']:9.2f} "
          f"{(med['on'] + sim) / (med['off'] + sim):19.2f}")
    print("reps off:", " ".join(f"{t:.4f}" for t in times["off"]), "| on:", " ".join(f"{t:.4f}" for t in times["on"]))
    import jax

    print(f"machine: {os.cpu_count()} CPUs, load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}, "
          f"JAX {jax.__version__} on {jax.devices()[0].device_kind}"
          + ("" if not args.inputs else f"; inputs from {args.inputs} (sim s/step as recorded there)"))


if __name__ == "__main__":
    main()

"""What the per-step signals of issue 74 cost per control step: the readout-features probe (a second forward pass,
--readout-features-every) and the action-consistency probe (--action-consistency; with --action-samples K on a
sampling head, K more draws), each against a plain policy on the same recorded closed-loop inputs, in one process.

A few short Lift episodes of the model are recorded first (`--episodes` seeds, `--steps` steps each, with the
checkpoint's conventions); then every policy steps through those inputs as fresh episodes, alternating policy by
policy within each rep so load drifts hit them alike. Per policy: seconds per step (median over reps of the mean over
all recorded steps), the ratio to the plain policy, the ratio of a whole closed-loop step (plus the recording's
median simulation step), and whether every executed action is bit-identical to the plain policy's (np.array_equal).
The consistency itself is computed by the probe's sink in the episode writer's thread, off the control loop: its
cost per step (ChunkHistory add + at on the recorded chunks) is printed apart.

    .venv/bin/python benchmarks/bench_failure_probes.py [--model models/octo-reference-robosuite] [--task Lift]
        [--episodes 2] [--steps 10] [--reps 3] [--samples K] [--json FILE]

`--samples K` adds a policy with --action-samples K (only for a head that samples: the tiny fixture's diffusion
head, `--model tests/fixtures/octo-reference/tiny`; the reference's L1 head refuses it). `--json FILE` writes the
figures as JSON.

Measured here (2 shared CPUs, load average 3-3.7 from other sessions, JAX 0.7.1 on CPU; 2 episodes x 10 steps,
3 reps), `--json` figures of commit-time runs:

    robosuite reference (L1 head)   s/step   x policy   x closed-loop step (sim 0.100 s)   actions bit-identical
      plain                         0.0232     1.00       1.00                              True
      readout features, every step  0.0421     1.82       1.15                              True
      action consistency            0.0239     1.03       1.01                              True
      (consistency in the sink: 119 us a step, in the writer thread)
    tiny fixture (diffusion head), --samples 4 (sim 0.081 s)
      plain                         0.0173     1.00       1.00                              True
      readout features, every step  0.0245     1.42       1.07                              True
      action consistency            0.0183     1.06       1.01                              True
      action consistency, K = 4     0.0748     4.33       1.58                              True

The readout pass is about one more forward pass without the head (every N-th step with N > 1 divides its share);
the consistency probe without samples is within the noise of the plain run; K samples cost about K forward passes.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import numpy as np  # noqa: E402

from harness.conventions import CheckpointConventions  # noqa: E402
from harness.policies import load_policy  # noqa: E402
from harness.policy import ClosedLoopPolicy  # noqa: E402


def record(env, policy: ClosedLoopPolicy, episodes: int, steps: int) -> tuple[list, float]:
    """([(seed, instruction, [observation per step])] of `episodes` closed-loop episodes, median simulation seconds
    per step)."""
    recorded, sim = [], []
    for seed in range(episodes):
        obs, info = env.reset(seed=seed)
        policy.reset(info["instruction"], seed=seed)
        observations = []
        for _ in range(steps):
            observations.append(obs)
            action = policy.step(obs).action
            start = time.perf_counter()
            obs, _, terminated, truncated, info = env.step(action)
            sim.append(time.perf_counter() - start)
            if terminated or truncated:
                break
        recorded.append((seed, info.get("instruction", ""), observations))
    return recorded, statistics.median(sim)


def replay(policy: ClosedLoopPolicy, recorded: list) -> tuple[float, np.ndarray, list]:
    """(mean policy seconds per step over every recorded step, the executed actions (steps, dim), the chunks and
    inferred flags per episode) of the policy stepping through the recorded inputs as fresh episodes."""
    actions, chunks, seconds, count = [], [], 0.0, 0
    for seed, instruction, observations in recorded:
        policy.reset(instruction, seed=seed)
        episode = []
        start = time.perf_counter()
        for obs in observations:
            step = policy.step(obs)
            actions.append(step.action)
            episode.append((step.chunk, step.inferred))
        seconds += time.perf_counter() - start
        count += len(observations)
        chunks.append(episode)
    return seconds / count, np.stack(actions), chunks


def sink_seconds(chunks: list) -> float:
    """Seconds per step of the consistency sink's arithmetic (ChunkHistory add + at) over the recorded chunks."""
    from harness.probes.action_consistency.measure import ChunkHistory

    start, count = time.perf_counter(), 0
    for episode in chunks:
        history = ChunkHistory()
        for t, (chunk, inferred) in enumerate(episode):
            if inferred:
                history.add(t, chunk)
                history.at(t)
            count += 1
    return (time.perf_counter() - start) / count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="models/octo-reference-robosuite")
    parser.add_argument("--task", default="Lift")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--samples", type=int, default=0, help="also --action-samples K (a sampling head only)")
    parser.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    args = parser.parse_args()
    model = load_policy(args.model)
    conventions = CheckpointConventions.read(args.model if os.path.isdir(args.model) else None)
    settings = {"plain": {}, "readout_features": {"readout_features_every": 1},
                "action_consistency": {"action_consistency": True}}
    if args.samples:
        settings[f"action_samples_{args.samples}"] = {"action_consistency": True, "action_samples": args.samples}
    policies = {label: model.closed_loop(conventions.policy_config(extra)) for label, extra in settings.items()}

    import envs

    env = envs.make(args.task, conventions.env_options({"masks": False, "fast_render": True}))
    try:
        recorded, sim = record(env, policies["plain"], args.episodes, args.steps)
    finally:
        env.close()
    first = {label: replay(policy, recorded) for label, policy in policies.items()}  # compile and warm up
    times = {label: [] for label in policies}
    for _ in range(args.reps):
        for label, policy in policies.items():
            times[label].append(replay(policy, recorded)[0])
    med = {label: statistics.median(t) for label, t in times.items()}
    plain_actions = first["plain"][1]
    steps = len(plain_actions)
    rows = {label: {"seconds_per_step": med[label], "ratio_policy": med[label] / med["plain"],
                    "ratio_closed_loop_step": (med[label] + sim) / (med["plain"] + sim),
                    "actions_bit_identical": bool(np.array_equal(first[label][1], plain_actions)),
                    "reps": times[label]} for label in policies}
    sink = sink_seconds(first["plain"][2])

    import jax

    machine = (f"{os.cpu_count()} CPUs, load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}, "
               f"JAX {jax.__version__} on {jax.devices()[0].device_kind}")
    print(f"model {args.model}, task {args.task}, {args.episodes} episodes x {args.steps} steps ({steps} steps), "
          f"{args.reps} reps; simulation {sim:.4f} s/step")
    print(f"{'policy':>22} {'s/step':>9} {'x policy':>9} {'x closed-loop step':>19} {'actions bit-identical':>22}")
    for label, row in rows.items():
        print(f"{label:>22} {row['seconds_per_step']:9.4f} {row['ratio_policy']:9.2f} "
              f"{row['ratio_closed_loop_step']:19.2f} {str(row['actions_bit_identical']):>22}")
    print(f"action consistency in the sink (writer thread): {sink * 1e6:.1f} us a step")
    print(f"machine: {machine}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"model": args.model, "task": args.task, "episodes": args.episodes, "steps": steps,
                       "reps": args.reps, "simulation_seconds_per_step": sim, "policies": rows,
                       "consistency_sink_seconds_per_step": sink, "machine": machine}, f, indent=2)
            f.write("\n")


if __name__ == "__main__":
    main()

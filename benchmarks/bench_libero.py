"""Cost of a LIBERO step against a robosuite task's: simulation, the process boundary, inference.

LIBERO runs in its own environment behind a server process (envs/libero_server.py); each control step sends the
action and receives the observation (images, masks' id images, state) over a pipe. This script times, in one run:

  robosuite Lift (RobosuiteEnv, in this process)         seconds per step
  LIBERO libero_object/0 (LiberoEnv -> server)           seconds per step in the driver, of which in the server
                                                          (simulation + rendering + segmentation), the rest being
                                                          the boundary (encode, pipe, decode, masks from ids)
  inference (random:octo-small-1.5, ClosedLoopPolicy.step)     seconds per step, on a LIBERO observation

for cameras agentview 256 + eye-in-hand 128 px, masks on and off, and prints the LIBERO/robosuite ratios.

    .venv/bin/python benchmarks/bench_libero.py [--steps 30] [--no-inference]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

import envs


def time_env(task: str, steps: int, masks: bool, action: np.ndarray) -> dict:
    """{step, server, reset, make} seconds (server: LIBERO only) for one env configuration."""
    start = time.perf_counter()
    env = envs.make(task, masks=masks)
    made = time.perf_counter() - start
    try:
        start = time.perf_counter()
        env.reset(seed=0)
        reset = time.perf_counter() - start
        for _ in range(3):
            env.step(action)
        server = 0.0
        start = time.perf_counter()
        for _ in range(steps):
            env.step(action)
            server += getattr(env, "last_server_seconds", 0.0)
        step = (time.perf_counter() - start) / steps
    finally:
        env.close()
    return {"make": made, "reset": reset, "step": step, "server": server / steps}


def time_inference(steps: int) -> float:
    from harness.policies import load_policy
    from harness.policy import PolicyConfig

    model = load_policy("random:octo-small-1.5")
    env = envs.make("libero_object/0")
    try:
        obs, info = env.reset(seed=0)
        policy = model.closed_loop(PolicyConfig())
        policy.reset(info["instruction"], seed=0)
        policy.step(obs)  # compile
        start = time.perf_counter()
        for _ in range(steps):
            policy.step(obs)
        return (time.perf_counter() - start) / steps
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--no-inference", action="store_true")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, MUJOCO_GL={os.environ.get('MUJOCO_GL', 'egl')}")
    action = np.array([0.002, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], np.float32)
    rows = []
    for masks in (False, True):
        robo = time_env("Lift", args.steps, masks, action)
        lib = time_env("libero_object/0", args.steps, masks, action)
        rows.append((masks, robo, lib))
    print(f"{'cameras 256+128':<22}{'robosuite Lift':>16}{'LIBERO step':>13}{'in server':>11}{'boundary':>10}"
          f"{'ratio':>7}{'LIBERO reset':>14}{'make':>7}")
    for masks, robo, lib in rows:
        boundary = lib["step"] - lib["server"]
        print(f"{'masks' if masks else 'no masks':<22}{robo['step']:>14.3f} s{lib['step']:>11.3f} s{lib['server']:>9.3f} s"
              f"{boundary:>8.3f} s{lib['step'] / robo['step']:>6.2f}x{lib['reset']:>12.2f} s{lib['make']:>6.1f} s")
    if not args.no_inference:
        inference = time_inference(max(args.steps // 3, 5))
        masks, robo, lib = rows[-1]
        print(f"inference (random:octo-small-1.5, one policy step): {inference:.3f} s; a closed-loop step with masks "
              f"costs about {robo['step'] + inference:.3f} s on robosuite, {lib['step'] + inference:.3f} s on LIBERO "
              f"({(lib['step'] + inference) / (robo['step'] + inference):.2f}x)")


if __name__ == "__main__":
    main()

"""Measures the scripted LIBERO-Object expert (reference_policies/libero_expert.py): success over tasks x initial states.

    python scripts/libero_expert.py [--tasks 0-9] [--states 10] [--out results/libero_expert.json]

Each episode goes through the policy's path: envs.make("libero_object/k", action_space="libero") -> LIBERO's own
environment behind the server process, reset(seed=s) = stored initial state s plus the settle steps, the suite's
280-step limit, LIBERO's success predicate. No cameras (the expert reads state), so no rendering. Writes one JSON
file with every episode and the machine it ran on; docs/libero.md quotes it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("MUJOCO_GL", "egl")

import envs  # noqa: E402
from envs.libero_tasks import get_libero_task  # noqa: E402
from reference_policies.libero_expert import run_expert_episode  # noqa: E402


def _range(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(t) for t in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="0-9", help="libero_object task indices, e.g. 0-9 or 0,3")
    parser.add_argument("--states", type=int, default=10, help="initial states 0..N-1 per task")
    parser.add_argument("--out", default="results/libero_expert.json")
    args = parser.parse_args()
    episodes, started = [], time.time()
    for k in _range(args.tasks):
        spec = get_libero_task(f"libero_object/{k}")
        env = envs.make(spec.name, cameras={}, action_space="libero")
        try:
            for state in range(args.states):
                t = time.time()
                result = run_expert_episode(env, spec.targets[0], state)
                episodes.append({"task": spec.name, "object": spec.targets[0], "state": state, **result,
                                 "seconds": round(time.time() - t, 2)})
                print(json.dumps(episodes[-1]), flush=True)
        finally:
            env.close()
    successes = sum(e["success"] for e in episodes)
    per_task = {}
    for e in episodes:
        per_task.setdefault(e["task"], [0, 0])
        per_task[e["task"]][0] += int(e["success"])
        per_task[e["task"]][1] += 1
    summary = {"successes": successes, "episodes": len(episodes), "rate": successes / max(len(episodes), 1),
               "per_task": {t: f"{s}/{n}" for t, (s, n) in per_task.items()},
               "seconds": round(time.time() - started, 1),
               "machine": f"{platform.machine()} {os.cpu_count()} cores, {platform.platform()}",
               "libero": envs.libero_env.libero_versions(), "episodes_detail": episodes}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(summary, indent=1) + "\n")
    print(f"expert: {successes}/{len(episodes)} ({summary['rate']:.0%}) -> {args.out}")


if __name__ == "__main__":
    main()

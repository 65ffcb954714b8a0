"""Cost of `--rerun save`: seconds per control step and recording size per 100 steps, on the reference policy.

Runs closed-loop episodes of the reference policy (models/octo-reference-robosuite, robosuite Lift, real JAX model,
real renderer, masks on) in one process, alternating two arms episode by episode so machine load hits both alike:

  baseline   the run's outputs without a recording (--png-every 0: arrays, metrics and the MP4)
  rerun      the same plus --rerun save (episode.rrd, written by the writer's background thread)

and prints each arm's mean seconds per step, the overhead of the rerun arm over the baseline, the process CPU time per
step of each arm (all threads: less sensitive to other processes' load than wall time), the recording sink's own
wall time per step in the background thread (episode.json timings.rerun), and the size of episode.rrd per 100 steps. Target (issue 30): at most 10% added to a step; the size is stated, not bounded.

    .venv/bin/python benchmarks/bench_rerun.py [--steps 100] [--episodes 3] [--fast-render] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("HF_HUB_OFFLINE", "1")

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=str(REPO / "models" / "octo-reference-robosuite"))
    parser.add_argument("--task", default="Lift")
    parser.add_argument("--steps", type=int, default=100, help="control steps per episode")
    parser.add_argument("--episodes", type=int, default=3, help="episodes per arm (seeds 0..n-1, the same for both)")
    parser.add_argument("--fast-render", action="store_true")
    parser.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = parser.parse_args()

    from harness.policies import load_policy
    from harness.run import execute
    from harness.run.settings import build_protocol

    def protocol(rerun: bool, seed: int, steps: int):
        return build_protocol({"task": [args.task], "model": args.model, "episodes": 1, "seed": seed,
                               "max_steps": steps, "png_every": 0, "fast_render": args.fast_render, "rerun": rerun})

    model = load_policy(args.model)
    arms = {"baseline": [], "rerun": []}  # per episode: (steps, seconds per step, sink seconds, rrd bytes)
    with tempfile.TemporaryDirectory() as out:
        for rerun in (False, True):  # warm-up: compile, open the renderer, import rerun
            execute(protocol(rerun, 0, 3), out, f"warmup_{rerun}", model=model, progress=False)
        for k in range(args.episodes):
            for arm in ("baseline", "rerun") if k % 2 == 0 else ("rerun", "baseline"):
                start, cpu = time.perf_counter(), time.process_time()
                summary = execute(protocol(arm == "rerun", k, args.steps), out, f"{arm}_{k}", model=model,
                                  progress=False)
                wall, cpu = time.perf_counter() - start, time.process_time() - cpu
                row = summary.rows[0]
                folder = summary.episode_dir(row)
                meta = json.loads((folder / "episode.json").read_text())
                rrd = folder / "episode.rrd"
                arms[arm].append({"steps": row.steps, "step_s": row.seconds_per_step, "wall_s": wall, "cpu_s": cpu,
                                  "sink_s": meta["timings"].get("rerun", 0.0),
                                  "rrd_bytes": rrd.stat().st_size if rrd.is_file() else 0})

    def mean(arm: str, key: str, per_step: bool = False) -> float:
        rows = arms[arm]
        if per_step:
            return sum(r[key] for r in rows) / sum(r["steps"] for r in rows)
        return sum(r[key] * r["steps"] for r in rows) / sum(r["steps"] for r in rows)

    base, rec = mean("baseline", "step_s"), mean("rerun", "step_s")
    result = {
        "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, {platform.platform()}",
        "model": args.model, "task": args.task, "steps": args.steps, "episodes_per_arm": args.episodes,
        "fast_render": args.fast_render,
        "baseline_s_per_step": base, "rerun_s_per_step": rec, "overhead": rec / base - 1,
        "sink_s_per_step": mean("rerun", "sink_s", per_step=True),
        "baseline_cpu_s_per_step": mean("baseline", "cpu_s", per_step=True),
        "rerun_cpu_s_per_step": mean("rerun", "cpu_s", per_step=True),
        "rrd_bytes_per_100_steps": 100 * mean("rerun", "rrd_bytes", per_step=True),
        "episodes": arms,
    }
    print(f"\n{args.model} on {args.task}, {args.episodes} episodes x {args.steps} steps per arm (alternated), "
          f"{'fast render' if args.fast_render else 'full render'}; {result['machine']}")
    print(f"{'arm':<10} {'s/step':>8}")
    print(f"{'baseline':<10} {base:>8.4f}")
    print(f"{'rerun':<10} {rec:>8.4f}   overhead {result['overhead']:+.1%} (target <= +10%)")
    cpu_base, cpu_rec = result["baseline_cpu_s_per_step"], result["rerun_cpu_s_per_step"]
    print(f"process CPU per step (all threads, episode incl. finishing its files): baseline {cpu_base:.4f} s, "
          f"rerun {cpu_rec:.4f} s ({cpu_rec / cpu_base - 1:+.1%})")
    print(f"recording sink (background thread, wall): {result['sink_s_per_step'] * 1000:.1f} ms per step")
    print(f"episode.rrd: {result['rrd_bytes_per_100_steps'] / 1e6:.2f} MB per 100 steps")
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()

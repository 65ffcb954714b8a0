"""What a run costs: seconds and megabytes per episode of the reference policy, with the disk estimate beside them.

Runs `octo-harness run` on the reference policy (Lift, seeds 0..EPISODES-1) three times, each into a fresh folder:
the defaults, `--png-every 0 --no-video` and `--fast-render`. For each it prints the steps, the seconds per step and
per episode (episodes after the first: the first also compiles), the run's megabytes per episode (every file's size,
run files included) and the estimate `run` compares with the free space (harness/run/space.py), computed at the
steps the episodes ran. Then the cost of the README's quick start, from the `--fast-render` run's per-step cost and
each task's mean steps in the model's eval.json. docs/running.md's table is this output.

    .venv/bin/python benchmarks/bench_run_cost.py [--episodes 2] [--out /tmp/run-cost] [--model PATH] [--task Lift]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = (("defaults", []), ("`--png-every 0 --no-video`", ["--png-every", "0", "--no-video"]),
           ("`--fast-render`", ["--fast-render"]))


def cpu_model() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        name = next(line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name"))
    except (OSError, subprocess.CalledProcessError, StopIteration):
        name = "unknown CPU"
    return f"{name}, {os.cpu_count()} cores"


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def measure(model: str, task: str, episodes: int, out: Path, name: str, flags: list[str]) -> dict:
    """One run: wall seconds, rows, bytes, and the estimate at the steps its episodes ran."""
    from harness.policies import load_policy
    from harness.run import space
    from harness.run.protocol import protocol_from_manifest
    from harness.run.store import RunStore

    shutil.rmtree(out / name, ignore_errors=True)
    command = [sys.executable, "-m", "harness.cli", "run", "--model", model, "--task", task, "--episodes",
               str(episodes), "--seed", "0", "--out", str(out), "--run-name", name, *flags]
    start = time.perf_counter()
    subprocess.run(command, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    run = out / name
    rows = [r for _, r in sorted(RunStore(run).load_rows().items())]
    manifest = json.loads((run / "manifest.json").read_text())
    protocol = protocol_from_manifest(manifest, run / "manifest.json", model_fingerprint=None, goal_fingerprint=None)
    shape = space.ModelShape.of(load_policy(protocol.model, text_tokenizer=protocol.text_tokenizer))
    estimate = space.RUN_BYTES + sum(sum(space.episode_bytes(protocol, r.task, shape, r.steps).values()) for r in rows)
    steady = rows[1:] or rows
    per_step = sum(r.seconds_per_step * r.steps for r in steady) / sum(r.steps for r in steady)
    return {"steps": sum(r.steps for r in rows) / len(rows), "per_step": per_step, "wall": wall,
            "episode_s": sum(r.seconds_per_step * r.steps for r in steady) / len(steady),
            "bytes": folder_bytes(run) / len(rows), "estimate": estimate / len(rows)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="models/octo-reference-robosuite")
    parser.add_argument("--task", default="Lift")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("/tmp/run-cost"))
    args = parser.parse_args()
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("MUJOCO_GL", "egl")
    found = {label: measure(args.model, args.task, args.episodes, args.out, f"cost{i}", flags)
             for i, (label, flags) in enumerate(CONFIGS)}
    from harness.runfolder.platform import git_commit

    print(f"{args.model}, {args.task}, {args.episodes} episodes (seeds 0..{args.episodes - 1}), CPU only.\n")
    print("| outputs | steps per episode | s per step | s per episode | MB per episode | estimate, MB | estimate / measured |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for label, m in found.items():
        print(f"| {label} | {m['steps']:.0f} | {m['per_step']:.2f} | {m['episode_s']:.0f} | {m['bytes'] / 1e6:.1f} | "
              f"{m['estimate'] / 1e6:.1f} | {m['estimate'] / m['bytes']:.2f} |")
    fast = found["`--fast-render`"]
    tasks = json.loads((ROOT / args.model / "eval.json").read_text())["tasks"]
    steps = sum(t["mean_steps"] for t in tasks) * 50
    print(f"\nQuick start (50 episodes of {', '.join(t['task'] for t in tasks)} with --fast-render, "
          f"{steps:.0f} steps at the eval.json mean steps): about {steps * fast['per_step'] / 3600:.1f} h and "
          f"{steps * fast['bytes'] / fast['steps'] / 1e9:.1f} GB; start-up (load, compile) "
          f"{fast['wall'] - fast['episode_s'] * args.episodes:.0f} s per run")
    print(f"\nProvenance: command `.venv/bin/python benchmarks/bench_run_cost.py`; commit `{(git_commit() or 'unknown')[:7]}`; "
          f"machine: {cpu_model()}, CPU only.")


if __name__ == "__main__":
    main()

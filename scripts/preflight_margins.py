"""Measure the pre-flight image check's margins on reference checkpoints over every task of their family.

For each checkpoint and task: the first frame (reset seed 0, as a run's first episode) of each camera, rendered
with the checkpoint's own conventions (its harness.toml, as a run takes them), scored against the checkpoint's
example frame under each image convention with both measures (harness.measures.orientation). Per camera it prints
the score of the training orientation, the vertical margin (its score minus that of the orientation that differs
from it by a vertical flip) and the mirror margin (minus that of its left-right mirror), and a summary per
checkpoint, camera and measure (smallest margin). The model cards quote the summaries with this script's provenance.

    .venv/bin/python scripts/preflight_margins.py models/octo-reference-robosuite --tasks Lift,Stack,PickPlaceCan
    .venv/bin/python scripts/preflight_margins.py models/octo-reference-libero-object --tasks libero_object
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def margins(model_dir: Path, tasks: list[str], seed: int = 0) -> list[dict]:
    import envs
    from envs.options import to_convention
    from harness.measures.orientation import MEASURES, orientation_scores
    from harness.policies import load_policy
    from harness.run.preflight import example_frames, first_frames
    from harness.run.settings import build_protocol

    model = load_policy(str(model_dir))
    examples = example_frames(model)
    protocol = build_protocol({"model": str(model_dir), "task": tasks})
    rows = []
    for task in protocol.tasks:
        options = protocol.env_for(task)
        env = envs.make(task, options)
        try:
            frames = first_frames(env, seed)
        finally:
            env.close()
        trained = options.image_convention
        vertical = "opengl" if trained in ("upright", "rot180") else "upright"
        mirror = {"upright": "rot180", "rot180": "upright"}.get(trained)
        for key, example in examples.items():
            upright = to_convention(frames[key], trained)
            for measure in MEASURES:
                s = orientation_scores(example, upright, measure)
                rows.append({"checkpoint": model_dir.name, "task": task, "camera": key, "measure": measure,
                             "trained": trained, "score": round(s[trained], 4),
                             "vertical_margin": round(s[trained] - s[vertical], 4),
                             "mirror_margin": round(s[trained] - s[mirror], 4) if mirror else None})
    return rows


def table(rows: list[dict]) -> str:
    """The model card's table: per camera and measure, over the tasks where the right orientation scores at least
    MIN_SCORE with the check's measure (it decides there; the others are counted apart: another scene)."""
    from harness.measures.orientation import MEASURE
    from harness.run.preflight import MIN_SCORE

    decides = {(r["task"], r["camera"]) for r in rows if r["measure"] == MEASURE and r["score"] >= MIN_SCORE}

    lines = ["| camera | measure | tasks decided (other scene) | score | vertical margin | mirror margin |",
             "|---|---|---|---|---|---|"]
    for camera in sorted({r["camera"] for r in rows}):
        for measure in sorted({r["measure"] for r in rows}):
            sel = [r for r in rows if r["camera"] == camera and r["measure"] == measure]
            decided = [r for r in sel if (r["task"], r["camera"]) in decides]
            mirrors = [r["mirror_margin"] for r in decided if r["mirror_margin"] is not None]
            span = lambda v: f"{min(v):.2f} to {max(v):.2f}" if v else "-"  # noqa: E731
            lines.append(f"| {camera} | {measure} | {len(decided)} ({len(sel) - len(decided)}) | "
                         f"{span([r['score'] for r in decided])} | {span([r['vertical_margin'] for r in decided])} | "
                         f"{span(mirrors)} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path, nargs="?")
    parser.add_argument("--tasks", help="comma-separated task names or a LIBERO suite")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--table", type=Path, help="print the table of this script's earlier output instead")
    args = parser.parse_args()
    if args.table is not None:
        print(table([json.loads(line) for line in args.table.read_text().splitlines() if line.startswith("{")]))
        return 0
    if args.checkpoint is None or not args.tasks:
        parser.error("give a checkpoint and --tasks (or --table FILE)")
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    rows = margins(args.checkpoint, args.tasks.split(","), args.seed)
    for row in rows:
        print(json.dumps(row))
    print(f"Provenance: command `python scripts/preflight_margins.py {args.checkpoint} --tasks {args.tasks} --seed "
          f"{args.seed}`; commit `{commit}`; machine: {_cpu()} ({platform.machine()}), {os.cpu_count()} cores, CPU only.")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())

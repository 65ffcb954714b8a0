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
    from harness.octo import load_pretrained
    from harness.run.preflight import example_frames, first_frames
    from harness.run.settings import build_protocol

    model = load_pretrained(str(model_dir))
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--tasks", required=True, help="comma-separated task names or a LIBERO suite")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    rows = margins(args.checkpoint, args.tasks.split(","), args.seed)
    for row in rows:
        print(json.dumps(row))
    print(f"# provenance: python scripts/preflight_margins.py {args.checkpoint} --tasks {args.tasks} --seed {args.seed}"
          f" at {commit} on {_cpu()} ({os.cpu_count()} CPUs)")
    print(f"{'camera':<14} {'measure':<6} {'tasks':>5} {'min score':>9} {'min vertical':>12} {'min mirror':>10} "
          f"{'max mirror':>10}")
    for camera in sorted({r["camera"] for r in rows}):
        for measure in sorted({r["measure"] for r in rows}):
            sel = [r for r in rows if r["camera"] == camera and r["measure"] == measure]
            mirrors = [r["mirror_margin"] for r in sel if r["mirror_margin"] is not None]
            print(f"{camera:<14} {measure:<6} {len(sel):>5} {min(r['score'] for r in sel):>9.3f} "
                  f"{min(r['vertical_margin'] for r in sel):>12.3f} "
                  f"{(min(mirrors) if mirrors else float('nan')):>10.3f} {(max(mirrors) if mirrors else float('nan')):>10.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

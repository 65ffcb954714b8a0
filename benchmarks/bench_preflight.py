"""The pre-flight check's cost against a one-episode run's wall time (issue 65: under 2%).

The check (harness.run.preflight.check_run) resets the env the driver already made and compares a few small
arrays; it is timed `--repeats` times on that env (median). The run is `octo-harness run`'s own pipeline
(harness.run.execute) with one episode of the task, its check included, timed from the call to its return
(model loading, env, compilation and the episode).

    .venv/bin/python benchmarks/bench_preflight.py [--model models/octo-reference-robosuite] [--task Lift]
    .venv/bin/python benchmarks/bench_preflight.py --model models/octo-reference-libero-object --task libero_object/0
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def time_check(protocol, model, repeats: int) -> tuple[float, list[dict]]:
    """(median seconds of one check, its findings) on the first task's env, made once as the driver makes it."""
    from harness.run.executor import CheckedEnv
    from harness.run.preflight import check_run

    dataset_key = model.closed_loop(protocol.policy).dataset_key
    checked = CheckedEnv(protocol, model, protocol.tasks[0])
    try:
        seconds = []
        for _ in range(repeats):
            start = time.perf_counter()
            block = check_run("warn", protocol, model, checked.env, protocol.seed, dataset_key)
            seconds.append(time.perf_counter() - start)
    finally:
        checked.close()
    return statistics.median(seconds), block["findings"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=str(ROOT / "models" / "octo-reference-robosuite"))
    parser.add_argument("--task", default="Lift")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    from harness.policies import load_policy
    from harness.run import execute
    from harness.run.settings import build_protocol

    protocol = build_protocol({"model": args.model, "task": [args.task], "png_every": 0, "no_video": True})
    model = load_policy(protocol.model)
    check, found = time_check(protocol, model, args.repeats)
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        summary = execute(protocol, out, "bench", progress=False)
        run = time.perf_counter() - start
    row = summary.rows[0]
    print(f"model {Path(args.model).name}, task {args.task}: episode of {row.steps} steps")
    print(f"{'pre-flight check (median of %d)' % args.repeats:<34} {check:8.3f} s")
    print(f"{'1-episode run (octo-harness run)':<34} {run:8.3f} s")
    print(f"{'ratio check / run':<34} {check / run:8.2%}")
    print("verdicts: " + ", ".join(f"{f['check']} {f['verdict']}" for f in found))
    return 0


if __name__ == "__main__":
    sys.exit(main())

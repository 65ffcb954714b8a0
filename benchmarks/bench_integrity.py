"""Cost of verifying a run folder's files (harness/runfolder/integrity.py) against reading them for analysis.

Writes one .npz of random float64 arrays of --megabytes, then times `file_digest` (size and sha256, what every
reader checks per data file) and `np.load` of every array in it, each the median of --repeats, and prints both
rates in MB/s and their ratio. docs/run-integrity.md quotes its numbers.

    .venv/bin/python benchmarks/bench_integrity.py [--megabytes 64] [--repeats 5]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from harness.runfolder.integrity import file_digest


def timed(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--megabytes", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "attention.npz"
        np.savez(path, **{f"a{i}": rng.random((args.megabytes << 20) // 8 // 4) for i in range(4)})
        size = path.stat().st_size / 2**20

        def load():
            with np.load(path) as z:
                for name in z.files:
                    z[name].sum()

        digest = timed(lambda: file_digest(path), args.repeats)
        read = timed(load, args.repeats)
    print(f"{platform.processor() or platform.machine()}, {size:.0f} MB file, median of {args.repeats}")
    print(f"file_digest (size + sha256): {size / digest:.0f} MB/s")
    print(f"np.load of every array:      {size / read:.0f} MB/s")
    print(f"verifying / reading: {digest / read:.2f}")


if __name__ == "__main__":
    main()

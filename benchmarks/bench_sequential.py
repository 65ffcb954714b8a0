"""Operating characteristics of the sequential regression test (harness.analysis.sequential), by simulation.

Prints, per scenario (baseline rate, candidate rate, correlation of the arms on a seed), the share of runs ending
REGRESSED / IMPROVED / HELD / UNDERPOWERED within the pair budget, the pairs used (mean, median) and the pairs a
fixed-size two-sided exact McNemar test needs for 80% / 95% power at the same discordance (exact unconditional
power, harness.analysis.paired.mcnemar_exact_sample_size; "-" above 5000 pairs).

    .venv/bin/python benchmarks/bench_sequential.py [--runs 2000] [--pairs 300]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from harness.analysis.paired import mcnemar_exact_sample_size  # noqa: E402
from harness.analysis.sequential import SequentialConfig, first_decisions, simulate_pairs  # noqa: E402

SCENARIOS = [(0.5, 0.5, 0.0), (0.8, 0.8, 0.5), (0.9, 0.9, 0.8), (0.8, 0.5, 0.0), (0.8, 0.5, 0.5), (0.8, 0.7, 0.0),
             (0.6, 0.8, 0.0)]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=2000)
    parser.add_argument("--pairs", type=int, default=300)
    parser.add_argument("--alpha", type=float, default=0.05)
    parser.add_argument("--max-drop", type=float, default=0.1)
    args = parser.parse_args()
    config = SequentialConfig(alpha=args.alpha, max_drop=args.max_drop)
    rng = np.random.default_rng(0)
    print(f"alpha {args.alpha}, max drop {args.max_drop}, {args.runs} runs of at most {args.pairs} pairs")
    print(f"{'base':>5} {'cand':>5} {'corr':>5} | {'REGR':>6} {'IMPR':>6} {'HELD':>6} {'UNDER':>6} | "
          f"{'mean':>6} {'median':>6} | {'fixed80':>7} {'fixed95':>7} | {'s':>5}")
    for base, cand, corr in SCENARIOS:
        start = time.perf_counter()
        y = simulate_pairs(base, cand, args.pairs, args.runs, rng, corr)
        verdict, used = first_decisions(y, config)
        share = {v: float(np.mean(verdict == v)) for v in ("REGRESSED", "IMPROVED", "HELD", "UNDERPOWERED")}
        pb, pc = float(np.mean(y == -1)), float(np.mean(y == 1))
        fixed = [mcnemar_exact_sample_size(pb, pc, args.alpha, power, limit=5000) for power in (0.8, 0.95)]
        fixed = ["-" if f is None else str(f) for f in fixed]
        print(f"{base:5.2f} {cand:5.2f} {corr:5.2f} | {share['REGRESSED']:6.3f} {share['IMPROVED']:6.3f} "
              f"{share['HELD']:6.3f} {share['UNDERPOWERED']:6.3f} | {used.mean():6.1f} {np.median(used):6.0f} | "
              f"{fixed[0]:>7} {fixed[1]:>7} | {time.perf_counter() - start:5.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

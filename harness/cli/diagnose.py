"""`octo-harness diagnose`: why each failed episode failed, and how early failure could have been predicted, from
finished run folders (harness.analysis.diagnose; no episode is run)."""

from __future__ import annotations

from pathlib import Path


def add_parser(sub) -> None:
    diag = sub.add_parser("diagnose", help="failure early warning and why each failed episode failed (finished runs)",
                          description="Predict each episode's failure from what is known up to step t (readout probe, "
                                      "action consistency, attention entropy, nuisance mass, against time and phase), "
                                      "fitted on some seeds and tested on the others, within conditions; and one line "
                                      "per failed episode. Writes diagnose.json, diagnose.md and failures.csv. "
                                      "docs/diagnose.md")
    diag.add_argument("runs", nargs="+", type=Path, metavar="RUN",
                      help="run folder(s), or a robustness grid folder (octo-harness robustness): its condition runs")
    diag.add_argument("--out", type=Path, default=None, help="output folder [first RUN/diagnose]")
    diag.add_argument("--folds", type=int, default=5, help="seed-disjoint folds for fitting and testing [5]")
    diag.add_argument("--resamples", type=int, default=2000,
                      help="seed-cluster bootstrap resamples for the 95%% intervals [2000]")
    diag.set_defaults(func=main)


def main(args) -> int:
    from harness.analysis.diagnose import diagnose, write
    from harness.cli.common import writing

    if args.folds < 2:
        raise ValueError(f"--folds must be at least 2 (fit on some seeds, test on others), got {args.folds}")
    if args.resamples < 100:
        raise ValueError(f"--resamples must be at least 100 for a percentile interval, got {args.resamples}")
    result = diagnose(args.runs, folds=args.folds, resamples=args.resamples)
    out = args.out or args.runs[0] / "diagnose"
    paths = writing(f"diagnose's outputs in {out}", "written", lambda: write(result, out))
    for line in result.lines:
        print(line)
    print(f"diagnose: {paths['markdown']} ({sum(t['episodes'] for t in result.tasks.values())} episodes, "
          f"{len(result.failures)} failed; failures.csv, diagnose.json)")
    return 0

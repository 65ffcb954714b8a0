"""`octo-harness report`: the HTML report of one or more runs (report.html, tables/*.csv, plots/*.png)."""

from __future__ import annotations

from pathlib import Path


def add_parser(sub) -> None:
    rep = sub.add_parser("report", help="HTML report comparing attention task by task (one or more runs)",
                         description="Aggregate the episodes of one or more runs into report.html (self-contained), "
                                     "tables/*.csv (long format) and plots/*.png.")
    rep.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR", help="run folder(s); several appear side by side")
    rep.add_argument("--out", type=Path, default=None, help="report folder [first RUN_DIR/report]")
    rep.add_argument("--bins", type=int, default=10, help="bins of normalised episode progress [10]")
    rep.add_argument("--resamples", type=int, default=2000, help="bootstrap resamples for the 95%% intervals [2000]")
    rep.add_argument("--margin", type=float, default=0.15,
                     help="a robustness cell HOLDS when its drop's upper confidence bound is below this [0.15]")
    rep.add_argument("--workers", type=int, default=None,
                     help="processes measuring runs made before measures were stored [up to 4 above 1 GB of attention]")
    rep.set_defaults(func=main)


def main(args) -> int:
    from harness.report.build import ReportOptions, build_report

    result = build_report(args.runs, args.out, ReportOptions(bins=args.bins, resamples=args.resamples, workers=args.workers,
                                                                  margin=args.margin))
    print(f"report: {result.html} ({result.episodes} episodes, {len(result.plots)} plots, {result.seconds:.1f} s)")
    return 0

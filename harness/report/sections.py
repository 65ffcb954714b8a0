"""The report's optional sections behind one interface: each reads the analysed runs once (`summarise`), gives its
CSV files (`tables`) and its HTML with its figures (`section`, drawing into the page's figure collector).

A section is present only when the runs hold what it reads (`section` returns "" otherwise) and then has an entry in
the page's contents. `sections()` is the order on the page: the per-step probes' sections first, in the registry's
order (harness.probes: each probe names its section, found here through the registry), then `SECTIONS`;
`harness.report.build` and `harness.report.page` loop over it, so a new section is one class here (and its module:
tables, figures, HTML), or the section its probe declares.

  Faithfulness  tables/faithfulness*.csv, interventions.csv   harness/report/faithfulness.py (the attribution probe's)
  (probes)      each registered probe's section, found through the registry (harness.probes)
  Phases        tables/phase_*.csv                             harness/report/phases.py
  Position      tables/position_*.csv                          harness/report/position.py
  Robustness    tables/robustness*.csv (perturbed runs)        harness/report/robustness.py
  Failures      tables/failures.csv (failed episodes)          harness/report/failures.py, failure_frames.py
  Grounding     tables/grounding_*.csv (LIBERO-Object runs)    harness/report/grounding.py
"""

from __future__ import annotations

from typing import Any, Protocol

from harness import probes
from harness.report import failures, faithfulness, grounding, phases, position, robustness
from harness.report.rundata import RunData
from harness.report.rundata import csv_bytes as _csv


class ReportSection(Protocol):
    name: str  # its heading and its entry in the page's contents
    anchor: str  # its id on the page; also its key in the summaries `summarise` made

    def summarise(self, runs: list[RunData], options) -> Any:
        """What `tables` and `section` both read, computed once (None: each computes what it needs)."""

    def tables(self, runs: list[RunData], summary: Any) -> dict[str, bytes]:
        """{csv file name: bytes} for tables/ ({} when the runs hold nothing for it)."""

    def section(self, runs: list[RunData], figures, summary: Any) -> str:
        """The section's HTML ("" when absent); its figures go through `figures.add(name, png, alt, caption)`."""


def _records(runs: list[RunData]) -> list:
    return [run.record for run in runs]


def _csv_files(tables: dict[str, tuple]) -> dict[str, bytes]:
    return {name: _csv(cols, rows) for name, (cols, rows) in tables.items()}


class Faithfulness:
    name, anchor = "Faithfulness", "faithfulness"  # runs that measured faithfulness or ran an intervention

    def summarise(self, runs, options):
        return None

    def tables(self, runs, summary):
        return faithfulness.tables(runs)

    def section(self, runs, figures, summary):
        return faithfulness.section(runs, figures)


class Phases:
    name, anchor = "Phases", "phases"  # runs that recorded task phases

    def summarise(self, runs, options):
        return [phases.summarise(run, options.resamples, options.seed) for run in runs]

    def tables(self, runs, summary):
        return phases.tables(runs, summary)

    def section(self, runs, figures, summary):
        return phases.section(runs, figures, summary)


class Position:
    name, anchor = "Position", "position"  # runs with attention controls

    def summarise(self, runs, options):
        return [position.summarise(run) for run in runs]

    def tables(self, runs, summary):
        return position.tables(runs, summary)

    def section(self, runs, figures, summary):
        return position.section(runs, figures, summary)


class Robustness:
    name, anchor = "Robustness", "robustness"  # perturbed runs

    def summarise(self, runs, options):
        return robustness.analyse(_records(runs), options.margin)  # None unless a run was perturbed

    def tables(self, runs, summary):
        return _csv_files(robustness.tables(_records(runs), summary))

    def section(self, runs, figures, summary):
        return robustness.section(_records(runs), figures, summary)


class Failures:
    name, anchor = "Failures", "failures"  # runs with a failed episode: diagnose's rows, stall frames beside successes

    def summarise(self, runs, options):
        return failures.summarise(runs)  # None unless an episode failed

    def tables(self, runs, summary):
        return failures.tables(summary if summary is not None else failures.summarise(runs))

    def section(self, runs, figures, summary):
        return failures.section(runs, figures, summary if summary is not None else failures.summarise(runs))


class Grounding:
    name, anchor = "Grounding", "grounding"  # runs that hold LIBERO-Object episodes

    def summarise(self, runs, options):
        return None

    def tables(self, runs, summary):
        return _csv_files(grounding.tables(_records(runs)))

    def section(self, runs, figures, summary):
        return grounding.section(_records(runs))


SECTIONS: tuple[ReportSection, ...] = (Phases(), Position(), Robustness(), Failures(), Grounding())  # after the probes' sections


def sections() -> tuple[ReportSection, ...]:
    """The page's sections in order: each registered probe's section (harness.probes, registry order; a class is
    made here), then SECTIONS."""
    found = [section() if isinstance(section, type) else section for _, section in probes.parts("section")]
    return (*found, *SECTIONS)

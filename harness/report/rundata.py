"""What the report knows about one run: its record, the analysed episode summaries, the long table rows and
lookups into them (arrays per task, outcome and metric), and the choices made from them (representative episode,
share categories). Plain data filled by harness.report.build, read by harness.report.page."""

from __future__ import annotations

import csv
import io
import math

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from harness.analysis import aggregate as agg
from harness.analysis.runs import EpisodeRecord, RunRecord


@dataclass
class RunData:
    """Everything the page needs about one run."""

    record: RunRecord
    label: str
    colour: str
    summaries: dict[tuple[str, int], agg.EpisodeSummary] = field(default_factory=dict)
    errors: dict[tuple[str, int], str] = field(default_factory=dict)  # episodes whose arrays could not be analysed
    rows: dict[str, list[tuple]] = field(default_factory=lambda: {"layers": [], "heads": [], "progress": []})
    success: dict[str, dict] = field(default_factory=dict)  # task -> success_summary(...) + counts
    headline: str | None = None  # e.g. mask_lift/image_primary/target
    cameras: list[str] = field(default_factory=list)

    def layer_values(self, task: str, metric: str, outcome: str = "all") -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        return self._index.get(("layers", task, outcome, metric))

    def head_values(self, task: str, metric: str, outcome: str = "all") -> np.ndarray | None:
        found = self._index.get(("heads", task, outcome, metric))
        return None if found is None else found[0]

    def progress_values(self, task: str, metric: str, layer: int, outcome: str = "all"):
        return self._index.get(("progress", task, outcome, metric, layer))

    def build_index(self) -> None:
        """(table, task, outcome, metric[, layer]) -> arrays, from the long rows."""
        index: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        index.update(_scatter(self.rows["layers"], lambda r: ("layers", r[1], r[8], r[4]), lambda r: (r[2],)))
        index.update(_scatter(self.rows["heads"], lambda r: ("heads", r[1], r[8], r[4]), lambda r: (r[2], r[3])))
        index.update(_scatter(self.rows["progress"], lambda r: ("progress", r[1], r[8], r[4], r[2]), lambda r: (r[10],)))
        self._index = index


def representative(run: RunData, task: str) -> EpisodeRecord | None:
    analysed = [e for e in run.record.task_episodes(task) if e.ok and (task, e.episode) in run.summaries]
    if not analysed:
        return None
    values = np.array([episode_headline(run, e) for e in analysed])
    return analysed[agg.representative_index(values)]


def episode_headline(run: RunData, e: EpisodeRecord) -> float:
    summary = run.summaries.get((e.task, e.episode))
    if summary is None or run.headline is None or run.headline not in summary.layer:
        return float("nan")
    return float(summary.layer[run.headline][-1])


def share_categories(runs: list[RunData]) -> list[tuple[str, str]]:
    """[(label, metric)] of the modality shares plus the earlier-timesteps share, in a fixed order."""
    metrics: list[str] = []
    for run in runs:
        for r in run.rows["layers"]:
            if r[4].startswith("share/") and r[4] not in metrics:
                metrics.append(r[4])
    order = ["primary", "wrist", "language", "readout"]
    metrics.sort(key=lambda m: (order.index(m[6:]) if m[6:] in order else len(order), m))
    out = [(m[6:], m) for m in metrics]
    if any(r[4] == "timestep_share/earlier" for run in runs for r in run.rows["layers"]):
        out.append(("earlier timesteps", "timestep_share/earlier"))
    return out


def _scatter(rows, key_of, position_of) -> dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Long rows (value, ci_low, ci_high at columns 5-7) -> {key: (value, low, high) arrays}, each row at its
    position (layer / (layer, head) / progress bin); positions no row names stay NaN."""
    grouped: dict[tuple, list[tuple]] = defaultdict(list)
    for r in rows:
        grouped[key_of(r)].append(r)
    out = {}
    for key, members in grouped.items():
        positions = [position_of(r) for r in members]
        shape = tuple(max(p[i] for p in positions) + 1 for i in range(len(positions[0])))
        v, lo, hi = (np.full(shape, np.nan) for _ in range(3))
        for r, pos in zip(members, positions):
            v[pos], lo[pos], hi[pos] = r[5], r[6], r[7]
        out[key] = (v, lo, hi)
    return out


def csv_bytes(columns, rows) -> bytes:
    """One CSV table of the report (tables/*.csv) as bytes: a header row, floats to 6 significant digits, non-finite
    values as empty cells."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow(["" if isinstance(v, float) and not math.isfinite(v) else (f"{v:.6g}" if isinstance(v, float) else v)
                         for v in row])
    return buffer.getvalue().encode()

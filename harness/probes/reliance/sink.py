"""The reliance probe's file: reliance.jsonl, one row per reliance step x camera x region (--reliance-every), in
harness.probes.reliance.measure's schema (the sink of harness.probes.reliance)."""

from __future__ import annotations

import json
from typing import Any

from harness.files import json_safe
from harness.outputs.data_files import write_lines
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink


class RelianceLines(Sink):
    """reliance.jsonl (--reliance-every): one row per reliance step x camera x region, in harness.probes.reliance.measure's
    schema, with the run, task, episode and seed in front; not written when no step measured reliance."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.rows: list[dict] = []
        self.seconds = 0.0

    def add(self, step: FinishedStep) -> None:
        reliance = step.record.probes.get("reliance")
        if reliance is None:
            return
        ids = {"run": self.meta.run, "task": self.meta.task, "episode": self.meta.episode, "seed": self.meta.seed}
        self.rows.extend({**ids, **row} for row in reliance.get("rows", ()))
        self.seconds += float(reliance.get("seconds", 0.0))

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        if not self.rows:
            return {}
        write_lines(self.dir / "reliance.jsonl", [json.dumps(json_safe(row)) for row in self.rows])
        return {"reliance": "reliance.jsonl"}

    def timings(self) -> dict[str, Any]:
        return {"reliance": round(self.seconds, 6)} if self.rows else {}

"""The attribution probe's files: attribution.npz (the maps at the steps that carry them) and faithfulness.jsonl
(when measured), written when the episode closes (the sink of harness.probes.attribution)."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from harness.files import json_safe, write_atomic
from harness.outputs.data_files import write_lines
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink


class AttributionFiles(Sink):
    """attribution.npz: step (n,), seconds (n,), map/<method>/<obs key> (n, rows, cols) float32 at the steps that
    carry maps; faithfulness.jsonl: one row per step x camera x method (harness.measures.faithfulness), when
    measured. Neither is written when no step carries an attribution."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.probes: list[tuple[int, dict]] = []  # (step, Probe result) at steps that carry one

    def add(self, step: FinishedStep) -> None:
        payload = step.record.probes.get("attribution")
        if payload is not None:
            self.probes.append((step.record.step, payload))

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        if not self.probes:
            return {}
        files = {}
        probes, meta = self.probes, self.meta
        names = list(dict.fromkeys((m, k) for _, a in probes for m, by in a["maps"].items() for k in by))
        arrays = {"step": np.asarray([s for s, _ in probes], np.int32),
                  "seconds": np.asarray([a.get("seconds", np.nan) for _, a in probes])}
        for method, key in names:
            arrays[f"map/{method}/{key}"] = np.stack([a["maps"][method][key] for _, a in probes]).astype(np.float32)
        write_atomic(self.dir / "attribution.npz", lambda f: np.savez(f, **arrays))
        files["attribution"] = "attribution.npz"
        lines = [json.dumps(json_safe({"run": meta.run, "task": meta.task, "episode": meta.episode, "seed": meta.seed,
                                       "step": step, **row}))
                 for step, a in probes for row in a.get("faithfulness", [])]
        if lines:
            write_lines(self.dir / "faithfulness.jsonl", lines)
            files["faithfulness"] = "faithfulness.jsonl"
        return files

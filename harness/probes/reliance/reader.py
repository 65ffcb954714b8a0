"""Region reliance of a finished run: the reliance.jsonl rows that the closed loop wrote (harness.probes.reliance.measure,
`--reliance-every N`) read back and summarised beside where the attention went (issue 45).

Nuisance reliance (`step_nuisance`, `nuisance_reliance`): the share of a camera's reliance on background and
distractors, named after the attention's measures (nuisance_mass, background_mass, distractor_mass,
nuisance_start): nuisance_reliance, background_reliance, distractor_reliance per step, and per episode their
means over the sampled steps plus nuisance_reliance_start (steps before robustness_measures.START_STEPS), on the
attention's camera (robustness_measures.CAMERA) by default. NUISANCE (background, distractors) is what the attention's
nuisance mass sums (harness.analysis.robustness). `attention_regions` sums the attention's mask mass into the
same regions (measure.REGION_TABLE); `read_rows`, `episode_reliance`, `add_reliance` and
`rows_by_step` (`view`'s rebuild of the map layer) read an episode's reliance.jsonl with the bounded readers.
"""

from __future__ import annotations

import fnmatch
import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from harness.analysis.robustness_measures import CAMERA, START_STEPS
from harness.probes.reliance.measure import REGION_TABLE, TASK_OBJECTS

NUISANCE = ("background", "distractors")


def step_nuisance(rows: Sequence[Mapping]) -> dict[tuple[int, str], dict[str, float]]:
    """Rows of `region_reliance` -> {(step, camera): {"nuisance_reliance", "background_reliance",
    "distractor_reliance"}}: the reliance shares of background plus distractors, and of each (0 for a region the
    camera does not have); nan where the camera's shares are null (nothing used at that step)."""
    out: dict[tuple[int, str], dict[str, float]] = {}
    for row in rows:
        entry = out.setdefault((int(row["step"]), row["camera"]),
                               {"nuisance_reliance": 0.0, "background_reliance": 0.0, "distractor_reliance": 0.0})
        share = row["reliance_share"]
        if share is None:
            entry.update(nuisance_reliance=math.nan, background_reliance=math.nan, distractor_reliance=math.nan)
            continue
        if row["region"] in NUISANCE:
            name = "background_reliance" if row["region"] == "background" else "distractor_reliance"
            entry[name] += float(share)
            entry["nuisance_reliance"] += float(share)
    return out


def nuisance_reliance(rows: Sequence[Mapping], camera: str = CAMERA) -> dict:
    """An episode's rows -> {"step": [sampled steps], "per_step": [nuisance_reliance per step], and the episode
    means over those steps (nan-ignoring; nan without any) "nuisance_reliance", "background_reliance",
    "distractor_reliance", "nuisance_reliance_start" (steps before START_STEPS)}: the counterpart of the attention's
    nuisance_mass / background_mass / distractor_mass / nuisance_start, on `camera`."""
    per = {s: v for (s, c), v in sorted(step_nuisance(rows).items()) if c == camera}
    steps = list(per)

    def mean(name: str, keep=lambda s: True) -> float:
        values = [per[s][name] for s in steps if keep(s) and not math.isnan(per[s][name])]
        return float(np.mean(values)) if values else math.nan

    return {"step": steps, "per_step": [per[s]["nuisance_reliance"] for s in steps],
            "nuisance_reliance": mean("nuisance_reliance"), "background_reliance": mean("background_reliance"),
            "distractor_reliance": mean("distractor_reliance"),
            "nuisance_reliance_start": mean("nuisance_reliance", lambda s: s < START_STEPS)}


FILE = "reliance.jsonl"
EPISODE_FIELDS = ("nuisance_reliance", "background_reliance", "distractor_reliance", "nuisance_reliance_start")


def attention_regions(mass: Mapping[str, float], regions: Sequence[str]) -> dict[str, float]:
    """One camera's attention mass per env mask name at one step ({name: mask_mass}, the attention's
    measures/layer/mask_mass/<camera>/<name> at a layer) -> {region: share} over `regions` (the regions the reliance
    rows of that camera and step hold), summing to 1: each mask's mass goes to its REGION_TABLE row (as
    `region_masks` partitions the pixels; the env's masks are disjoint), the remainder (task_objects, or LIBERO's
    background) gets what no mask holds (1 - their sum, at least 0); {} when the camera's map has no mass (nan)."""
    mass = {k: float(v) for k, v in mass.items()}
    if any(math.isnan(v) for v in mass.values()):
        return {}
    out: dict[str, float] = {}
    used: set[str] = set()
    for region, sources, unless in REGION_TABLE:
        if any(u in mass for u in unless):
            continue
        names = [k for k in mass if k not in used and any(fnmatch.fnmatchcase(k, s) for s in sources)]
        if names:
            used.update(names)
            out[region] = sum(mass[k] for k in names)
    rest = max(0.0, 1.0 - sum(out.values()))
    remainder = TASK_OBJECTS if "background" in out else "background"
    out[remainder] = out.get(remainder, 0.0) + rest
    kept = {r: out.get(r, 0.0) for r in regions}
    total = sum(kept.values())
    return {r: v / total for r, v in kept.items()} if total > 0 else {}


def read_rows(path) -> list[dict]:
    """An episode's reliance.jsonl -> its rows, read with the bounded readers (harness.bounded: size, depth); a
    damaged file raises ValueError (or OSError) naming the file and line, for the caller to note, not crash on."""
    from harness.bounded import loads_json, read_jsonl_text

    rows = []
    for number, line in enumerate(read_jsonl_text(path, errors="strict").splitlines(), 1):
        if line.strip():
            row = loads_json(line, f"{path} line {number}")
            if not isinstance(row, dict) or not {"step", "camera", "region", "reliance_share"} <= set(row):
                raise ValueError(f"{path} line {number}: not a reliance row (step, camera, region, reliance_share)")
            rows.append(row)
    return rows


def by_step(directory: str | Path) -> dict[int, dict]:
    """The probe's reader (harness.probes.Probe.reader): an episode folder's payloads by step (`rows_by_step`)."""
    return rows_by_step(directory)


def rows_by_step(directory: str | Path) -> dict[int, dict]:
    """An episode folder's reliance.jsonl -> {step: {"rows": [its rows]}} ({} without the file), as a step record's
    `reliance` holds them, for `view`'s rebuild. A row of the wrong types is a ValueError naming the file and row."""
    path = Path(directory) / FILE
    if not path.is_file():
        return {}
    out: dict[int, dict] = {}
    for number, row in enumerate(read_rows(path), 1):
        problem = _row_problem(row)
        if problem:
            raise ValueError(f"{path} row {number}: {problem}; repair the file or re-create the run "
                             "(octo-harness run ... --overwrite)")
        out.setdefault(int(row["step"]), {"rows": []})["rows"].append(row)
    return out


def _row_problem(row: Mapping) -> str | None:
    def number(value) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0

    if not isinstance(row["step"], int) or isinstance(row["step"], bool) or row["step"] < 0:
        return f"step must be a step index, got {row['step']!r}"
    for key in ("camera", "region"):
        if not isinstance(row[key], str):
            return f"{key} must be a name, got {row[key]!r}"
    for key in ("reliance_share", "reliance_per_pixel"):
        if row.get(key) is not None and not number(row[key]):
            return f"{key} must be a number >= 0 or null, got {row[key]!r}"
    return None


def episode_reliance(path, camera: str = CAMERA) -> dict:
    """reliance.jsonl -> {EPISODE_FIELDS: episode means} (`nuisance_reliance` on `camera`); nan when the camera has
    no sampled step."""
    means = nuisance_reliance(read_rows(path), camera)
    return {k: means[k] for k in EPISODE_FIELDS}


def add_episode_measures(rows: Sequence, records) -> tuple[list, list[str]]:
    """The probe's per-episode measures for a robustness grid (harness.report.robustness reads them through the
    registry): `add_reliance`."""
    return add_reliance(rows, records)


def add_reliance(rows: Sequence, records) -> tuple[list, list[str]]:
    """robustness.EpisodeRow rows (robustness.collect) -> (the rows with EPISODE_FIELDS read from each episode's
    reliance.jsonl, where the episode has one; notes): a damaged file is a note and leaves its fields nan."""
    from dataclasses import replace

    episodes = {(record.name, e.task, e.episode): e for record in records for e in record.episodes}
    out, notes = [], []
    for row in rows:
        e = episodes.get((row.run, row.task, row.episode))
        if e is not None and e.ok and (e.directory / FILE).is_file():
            try:
                row = replace(row, **episode_reliance(e.directory / FILE))
            except (OSError, ValueError, KeyError, TypeError) as exc:
                notes.append(f"{row.run}/{row.task}/episode_{row.episode}: unreadable {FILE} ({exc})")
        out.append(row)
    return out, notes



"""The report's Reliance section: where the policy looks beside what it relies on, region by region (issue 45).

Runs made with `--reliance-every N` write each episode's `reliance.jsonl` (harness.probes.reliance.measure: per sampled
step, camera and labelled region, the change of the predicted chunk when the region is replaced, its reliance per
pixel and its reliance share). Beside each step's reliance shares this section puts the attention shares of the same
regions at the same steps: the readout attention mass (head mean, the camera's map at the current timestep) of the
model's LAST layer on each env mask, as attention.npz stores it (measures/layer/mask_mass/<camera>/<mask>), gathered
into the reliance regions (reliance.attention_regions) and normalised over the regions the reliance rows hold, so
both shares sum to 1 per camera and step. Steps where the camera was not used (reliance shares null) are left out of
both.

Per run x task x camera (the run's condition: its perturbation, or "nominal"):
  reliance_share, attention_share   mean over episodes of each episode's mean over its sampled steps (a region a
                                    step lacks counts 0 there, so the shares still sum to 1)
  reliance_per_pixel                the same mean over the steps where the region had pixels
  spearman                          the agreement of the two shares per step: Spearman's rank correlation over the
                                    regions (sanity.spearman; steps where either share is constant left out),
                                    averaged per seed, then over seeds with a 95% seed-cluster bootstrap interval
                                    (bootstrap.bootstrap_mean_ci over the seeds: a seed's steps move together)
and a short verdict line per task and camera names the region where they disagree most (largest |reliance share -
attention share|); the agreement is a table per camera (issue 67 item 4).

`summarise(runs, resamples, seed)` -> (rows of COLUMNS, notes); `tables(summary)` -> {"reliance.csv"} ({} without
reliance files); `section(summary, figures)` -> HTML ("" without). Every number on the page is in reliance.csv.
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

from harness.analysis.bootstrap import bootstrap_mean_ci
from harness.probes.reliance.reader import FILE, attention_regions, read_rows
from harness.probes.reliance.measure import REGION_TABLE, TASK_OBJECTS
from harness.analysis.robustness import run_condition
from harness.analysis.sanity import spearman
from harness.bounded import open_npz
from harness.report import html as H
from harness.report.figures_file import markdown_table
from harness.report.rundata import csv_bytes

COLUMNS = ("run", "task", "condition", "level", "camera", "region", "reliance_per_pixel", "reliance_share",
           "attention_share", "episodes", "steps", "spearman", "spearman_ci_low", "spearman_ci_high", "spearman_seeds")
ORDER = tuple(r for r, _, _ in REGION_TABLE[:-2]) + (TASK_OBJECTS,) + tuple(r for r, _, _ in REGION_TABLE[-2:])
MASS = "measures/layer/mask_mass/"


def _condition(manifest: dict) -> tuple[str, int]:
    found = run_condition(manifest)
    if found is None:  # several perturbations at once: named as given
        return str((manifest.get("protocol") or {}).get("perturb")), -1
    return found


def _mask_mass(path, cameras) -> dict[str, dict[int, dict[str, float]]]:
    """attention.npz -> {camera: {step: {mask name: last-layer mask mass}}} ({} without the file or the measures)."""
    if not path.is_file():
        return {}
    out: dict[str, dict[int, dict[str, float]]] = {}
    with open_npz(path) as z:
        files = list(z.files)
        steps = [int(s) for s in np.asarray(z["step"])] if "step" in files else None
        for key in files:
            if not key.startswith(MASS):
                continue
            camera, _, name = key[len(MASS):].partition("/")
            if camera not in cameras or "/" in name:
                continue
            values = np.asarray(z[key], np.float64)
            values = values[:, -1] if values.ndim == 2 else values
            for i, value in enumerate(values):
                step = steps[i] if steps is not None and i < len(steps) else i
                out.setdefault(camera, {}).setdefault(step, {})[name] = float(value)
    return out


def _episode_steps(rows: list[dict], mass: dict) -> dict[str, list[dict]]:
    """{camera: [{"step", "reliance": {region: share}, "attention": {region: share} or {}, "per_pixel": {region:
    value}}]} for the steps where the camera was used."""
    by = defaultdict(list)
    for row in rows:
        by[(int(row["step"]), row["camera"])].append(row)
    out: dict[str, list[dict]] = defaultdict(list)
    for (step, camera), items in sorted(by.items()):
        if any(r["reliance_share"] is None for r in items):
            continue
        regions = [r["region"] for r in items]
        at = (mass.get(camera) or {}).get(step)
        out[camera].append({"step": step, "reliance": {r["region"]: float(r["reliance_share"]) for r in items},
                            "attention": attention_regions(at, regions) if at else {},
                            "per_pixel": {r["region"]: float(r["reliance_per_pixel"]) for r in items
                                          if r.get("reliance_per_pixel") is not None}})
    return out


def _nanmean(values) -> float:
    v = np.asarray([x for x in values if math.isfinite(x)], np.float64)
    return float(v.mean()) if v.size else math.nan


def read_groups(runs) -> tuple[dict, list[str]]:
    """{(run label, task, condition, level, camera): [(seed, steps of one episode)]} and notes (damaged files)."""
    groups: dict[tuple, list] = defaultdict(list)
    notes = []
    for run in runs:
        record = getattr(run, "record", run)
        label = getattr(run, "label", record.name)
        condition, level = _condition(record.manifest)
        for e in record.episodes:
            path = e.directory / FILE
            if not (e.ok and path.is_file()):
                continue
            try:
                rows = read_rows(path)
                mass = _mask_mass(e.attention_path, {r["camera"] for r in rows})
                steps = _episode_steps(rows, mass)
            except (OSError, ValueError, KeyError, TypeError) as exc:
                notes.append(f"{label}/{e.task}/episode_{e.episode}: unreadable {FILE} or attention.npz ({exc}); "
                             "left out of the Reliance section")
                continue
            for camera, items in steps.items():
                seed = e.seed if e.seed is not None else -1 - e.episode
                groups[(label, e.task, condition, level, camera)].append((seed, items))
    return groups, notes


def summarise(runs, resamples: int = 2000, seed: int = 0) -> tuple[list[tuple], list[str]]:
    """(rows of COLUMNS: one per run x task x camera x region, regions in ORDER; notes)."""
    groups, notes = read_groups(runs)
    out = []
    for (label, task, condition, level, camera), episodes in groups.items():
        present = {r for _, items in episodes for s in items for r in s["reliance"]}
        regions = [r for r in ORDER if r in present] + sorted(present - set(ORDER))
        values = {r: {"reliance": [], "attention": [], "per_pixel": []} for r in regions}
        by_seed: dict[int, list[float]] = defaultdict(list)
        steps = 0
        for episode_seed, items in episodes:
            for r in regions:
                values[r]["reliance"].append(_nanmean([s["reliance"].get(r, 0.0) for s in items]))
                values[r]["attention"].append(_nanmean([s["attention"].get(r, 0.0) for s in items if s["attention"]]))
                values[r]["per_pixel"].append(_nanmean([s["per_pixel"][r] for s in items if r in s["per_pixel"]]))
            for s in items:
                if not s["attention"]:
                    continue
                steps += 1
                rho = spearman(np.array([s["reliance"].get(r, 0.0) for r in regions]),
                               np.array([s["attention"].get(r, 0.0) for r in regions]))
                if math.isfinite(rho):
                    by_seed[episode_seed].append(rho)
        seeds = np.array([np.mean(v) for v in by_seed.values()], np.float64)
        if seeds.size:
            mean, low, high, n = (float(x) for x in bootstrap_mean_ci(seeds, resamples=resamples, seed=seed))
        else:
            mean, low, high, n = math.nan, math.nan, math.nan, 0
        for r in regions:
            out.append((label, task, condition, level, camera, r, _nanmean(values[r]["per_pixel"]),
                        _nanmean(values[r]["reliance"]), _nanmean(values[r]["attention"]), len(episodes), steps,
                        mean, low, high, int(n)))
    return out, notes


def tables(summary) -> dict[str, bytes]:
    rows, _ = summary
    return {"reliance.csv": csv_bytes(COLUMNS, rows)} if rows else {}


def disagreement(rows: list[tuple]) -> str:
    """A verdict line (at most about 25 words) from the CSV rows of one run x task x camera: the region with the
    largest |reliance share - attention share|. The agreement over regions is agreement_row's."""
    first = rows[0]
    where = f"{first[1]}, {first[4]}"
    pairs = [(abs(r[7] - r[8]), r) for r in rows if math.isfinite(r[7]) and math.isfinite(r[8])]
    if not pairs:
        return f"{where}: no attention shares to compare the reliance with (attention.npz has no mask masses)."
    gap, r = max(pairs, key=lambda p: p[0])
    more = "relied on more than looked at" if r[7] > r[8] else "looked at more than relied on"
    return (f"{where}: largest gap on {r[5]}, {100 * r[7]:.0f}% of the reliance against {100 * r[8]:.0f}% of the "
            f"attention ({more}).")


def figure(task: str, rows: list[tuple]) -> bytes:
    """Attention share beside reliance share per region, one panel per camera."""
    from harness.report.figures import _figure, _png

    cameras = list(dict.fromkeys(r[4] for r in rows))
    fig = _figure(4.2 * len(cameras) + 0.6, 3.4)
    axes = np.atleast_1d(fig.subplots(1, len(cameras), squeeze=False)[0])
    for ax, camera in zip(axes, cameras):
        cam = [r for r in rows if r[4] == camera]
        x = np.arange(len(cam))
        ax.bar(x - 0.2, [r[8] for r in cam], 0.4, label="attention share", color="#4c78a8")
        ax.bar(x + 0.2, [r[7] for r in cam], 0.4, label="reliance share", color="#f58518")
        ax.set_xticks(x)
        ax.set_xticklabels([r[5] for r in cam], rotation=30, ha="right", fontsize=8)
        ax.set_ylim(0, 1)
        ax.set_title(camera, fontsize=10)
    axes[0].set_ylabel("share of the camera")
    axes[0].legend(fontsize=7, framealpha=0.4)
    fig.suptitle(task, fontsize=11)
    fig.subplots_adjust(bottom=0.28, top=0.84, wspace=0.25)
    return _png(fig)


AGREEMENT_HEADER = ("camera", "Spearman over regions per step: mean", "95% seed-cluster", "seeds", "steps", "episodes")


def agreement_row(rows: list[tuple]) -> tuple[str, ...]:
    """One camera's agreement of the two shares as table cells (AGREEMENT_HEADER); 'no step' where neither ranks."""
    r = rows[0]
    if r[14] == 0:
        return (r[4], "no step where both shares rank the regions", "-", "0", str(r[10]), str(r[9]))
    return (r[4], H.fmt(r[11], 2), f"[{H.fmt(r[12], 2)}, {H.fmt(r[13], 2)}]", str(r[14]), str(r[10]), str(r[9]))


def section(summary, figures) -> str:
    rows, notes = summary
    if not rows and not notes:
        return ""
    body = [H.note("Where the policy looks beside what it relies on. Reliance share: the region's share of the change "
                   "of the predicted action chunk when each labelled region of a camera is replaced in turn "
                   "(--reliance-every, --reliance-fill); attention share: the readout attention mass of the model's "
                   "last layer (head mean) on the same region's masks at the same steps, normalised over the same "
                   "regions, so both sum to 1 per camera. Agreement: Spearman's rank correlation of the two over the "
                   "regions at each step. Numbers: tables/reliance.csv.")]
    body += [H.banner(n) for n in notes]
    for key in dict.fromkeys(r[:4] for r in rows):
        label, task, condition, level = key
        group = [r for r in rows if r[:4] == key]
        name = condition if condition == "nominal" else f"{condition} level {level}"
        body.append(H.section(f"{task}: {name} (run {label})", "", level=3))
        cameras = list(dict.fromkeys(r[4] for r in group))
        for camera in cameras:
            body.append(H.Raw(f"<p>{H.esc(disagreement([r for r in group if r[4] == camera]))}</p>"))
        body.append(H.table(AGREEMENT_HEADER, [agreement_row([r for r in group if r[4] == c]) for c in cameras],
                            numeric=(3, 4, 5)))
        body.append(figures.add(f"reliance_{H.anchor_id(task)[2:]}_{H.anchor_id(label)[2:]}_{condition}_{level}",
                                figure(task, group), f"reliance {task}",
                                "Attention share (last layer) beside reliance share per region and camera."))
        body.append(H.table(("camera", "region", "attention share", "reliance share", "reliance per pixel",
                             "episodes"),
                            [(r[4], r[5], H.fmt(r[8], 2), H.fmt(r[7], 2), H.fmt(r[6], 3), r[9]) for r in group],
                            numeric=(2, 3, 4, 5)))
    return H.section("Reliance", "".join(str(b) for b in body), anchor="reliance")


SECTION = "## Reliance"


def markdown(records, note: str = "") -> str:
    """The Reliance section as Markdown (EVAL.md): per run and task, a verdict line per camera (where attention and
    reliance disagree most), the agreement table per camera and a table of attention share beside reliance share
    per region (the numbers of reliance.csv)."""
    rows, notes = summarise(records)
    if not rows:
        raise ValueError("no run here has reliance.jsonl: give runs made with --reliance-every")
    lines = [SECTION, "", note, ""] if note else [SECTION, ""]
    lines += [f"- {n}" for n in notes] + ([""] if notes else [])
    for key in dict.fromkeys(r[:4] for r in rows):
        label, task, condition, level = key
        group = [r for r in rows if r[:4] == key]
        name = condition if condition == "nominal" else f"{condition} level {level}"
        lines += [f"### {task}: {name} (run {label})", ""]
        cameras = list(dict.fromkeys(r[4] for r in group))
        lines += [f"- {disagreement([r for r in group if r[4] == camera])}" for camera in cameras]
        lines += ["", *markdown_table(AGREEMENT_HEADER, [agreement_row([r for r in group if r[4] == c]) for c in cameras],
                                      rule="|---|---:|---|---:|---:|---:|")]
        lines += ["", "| camera | region | attention share | reliance share | reliance per pixel | episodes |",
                  "|---|---|---:|---:|---:|---:|"]
        lines += [f"| {r[4]} | {r[5]} | {H.fmt(r[8], 2)} | {H.fmt(r[7], 2)} | {H.fmt(r[6], 3)} | {r[9]} |"
                  for r in group]
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    from harness.report.eval_md import section_main

    return section_main(argv, "python -m harness.probes.reliance.report", "Write the Reliance section of an EVAL.md "
                        "from runs made with --reliance-every.", markdown)


if __name__ == "__main__":
    raise SystemExit(main())


class Section:
    """The reliance probe's report section (harness.report.sections finds it through the registry): runs with
    reliance.jsonl (--reliance-every)."""

    name, anchor = "Reliance", "reliance"

    def summarise(self, runs, options):
        return summarise(runs, options.resamples, options.seed)

    def tables(self, runs, summary):
        return tables(summary)

    def section(self, runs, figures, summary):
        return section(summary, figures)

"""Robustness across perturbation conditions: success per (task, condition, level), attention on nuisances, and
the shift of attention a perturbation causes at step 0. Pure functions over run records and arrays.

Runs are grouped by their protocol's `perturb` (envs.perturbations): one perturbation -> (condition, level); no
perturbation -> the nominal run, level 0 of every condition. Per finished episode (from attention.npz, primary
camera `image_primary`, the model's last layer; harness.analysis.robustness_measures):
  nuisance_mass   attention mass on the background plus every distractor (neither robot, target nor another task
                  object), mean over the episode's steps
  target_lift     mask_lift of the target, mean over steps
  shift_js/<l>    for a perturbed episode and the nominal episode of the same task and seed: Jensen-Shannon
                  divergence (bits) of the two step-0 readout attention rows of layer l (mean over heads and
                  readouts, normalised over all keys; the same model gives the same keys)
  lift_change     step-0 target lift, perturbed minus nominal
  nuisance_start  nuisance mass over the first START_STEPS steps only: a failed episode runs to the step limit and
                  wanders, so the episode mean partly measures the outcome; the start is measured before it
Content-only (runs with `--attention-controls` including `blank`; controls.npz beside attention.npz): at each
control step the camera's map (readouts and heads averaged, last layer) has its blank-frame part removed
(harness.analysis.position.content_only: max(real - blank, 0), renormalised), and the same measures are read off it:
  nuisance_content, target_lift_content, nuisance_start_content   over the control steps only (nan without them)
A map whose nuisance attention is all bound to position keeps it on the blank frame and shows none content-only.
Association of nuisance mass with success, per task across episodes and conditions: the point-biserial
correlation (Pearson r of a 0/1 variable with a continuous one) with a 95% interval by Fisher's z (n - 3), which
assumes independent episodes, and a seed-cluster bootstrap interval (seeds resampled with all their episodes across
conditions, which share the scene's seed): the verdict reads the cluster interval. For the episode mean, for the
episode mean centred per run (within a condition: a perturbation that lowers both success and nuisance mass makes
a pooled association by itself), and for the start; each on the raw maps and, where any episode has controls,
on the content-only maps (`map` column: "raw" or "content").
Which condition breaks a task (`paired_rows`): each perturbed cell is paired with the nominal run's episodes of the
same task and seed (both ran to an outcome), tested by the exact McNemar test, and the p-values are Holm-adjusted over
the task's perturbed cells (the family-wise error the regression gate controls). Each cell gets one verdict:
  BREAKS        its adjusted p <= alpha and it lost successes;
  HOLDS         not BREAKS, and a drop larger than the margin (default MARGIN, 15 points; `--margin`) is ruled out:
                the upper confidence bound of the drop (Newcombe's interval at 1 - alpha / cells, Bonferroni over the
                task's cells) is within the margin and the exact test of "a drop >= margin" rejects: the same test
                as compare's HELD (harness.analysis.paired.equivalent);
  UNDETERMINED  neither: the data can tell neither a break nor the absence of one the size of the margin.
Each cell's row gives the smallest drop it could have detected (`detectable_drop`, `paired.detectable_loss`): at 20
pairs and Holm over 21 cells, a cell breaks only with 10 or more lost pairs and none gained (a drop of 50 points).
The text per task is short (issue 67 item 4): `verdict_line` (at most about 25 words) and `association_table`.
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass, fields

import numpy as np

from envs.perturbations import parse_perturb
from harness.analysis.paired import (PairedCounts, detectable_loss, difference_interval, equivalent,
                                     holm_adjust, mcnemar_exact)
from harness.analysis.robustness_measures import START_STEPS, episode_measures, js_divergence_bits
from harness.measures.stats import wilson_interval
from harness.verdicts import CellVerdict  # BREAKS, UNDETERMINED, HOLDS (see the module docstring)

CLUSTER_RESAMPLES = 2000
MIN_CLASS = 5
MAPS = ("raw", "content")  # the attention map a figure uses: raw, or content-only (blank-frame part removed)
MARGIN = 0.15  # HOLDS rules out a drop in success rate larger than this
ALPHA = 0.05


@dataclass(frozen=True)
class EpisodeRow:
    run: str
    task: str
    condition: str  # e.g. "camera@image_primary"; "nominal" for the nominal run
    level: int
    seed: int
    episode: int
    status: str
    success: bool
    nuisance_mass: float
    target_lift: float
    distractor_mass: float
    background_mass: float
    nuisance_start: float = math.nan
    nuisance_content: float = math.nan  # the same measures on the content-only maps at the control steps
    target_lift_content: float = math.nan
    nuisance_start_content: float = math.nan
    nuisance_reliance: float = math.nan  # reliance.jsonl (--reliance-every): the reliance share of background +
    background_reliance: float = math.nan  # distractors, and of each, mean over the sampled steps; nan without it
    # (filled by harness.probes.reliance.reader.add_reliance: this module cannot import it)
    distractor_reliance: float = math.nan
    nuisance_reliance_start: float = math.nan

    def nuisance(self, map_: str = "raw") -> tuple[float, float]:
        """(episode mean, first START_STEPS steps) of the nuisance mass on the raw or content-only map."""
        if map_ == "content":
            return self.nuisance_content, self.nuisance_start_content
        if map_ == "reliance":  # not an attention map: the share of the action's dependence (--reliance-every)
            return self.nuisance_reliance, self.nuisance_reliance_start
        return self.nuisance_mass, self.nuisance_start


def run_condition(manifest: dict) -> tuple[str, int] | None:
    """(condition, level) of a run from its manifest; ("nominal", 0) without perturbation; None with several."""
    perturbations = parse_perturb((manifest.get("protocol") or {}).get("perturb"))
    if not perturbations:
        return ("nominal", 0)
    if len(perturbations) > 1:
        return None
    return (perturbations[0].condition, perturbations[0].level)


def is_perturbed(records) -> bool:
    """Whether any run of `records` was made with a perturbation (the report then adds its Robustness section)."""
    return any((r.manifest.get("protocol") or {}).get("perturb") for r in records)


def point_biserial(success, values, confidence: float = 0.95) -> tuple[float, float, float, int]:
    """(r, ci_low, ci_high, n): Pearson correlation of 0/1 `success` with `values` (nan pairs dropped), 95% interval by
    Fisher's z transform with standard error 1/sqrt(n - 3); nan where n < 4 or a variable is constant."""
    from scipy.stats import norm

    s = np.asarray(success, np.float64)
    v = np.asarray(values, np.float64)
    keep = np.isfinite(s) & np.isfinite(v)
    s, v = s[keep], v[keep]
    n = int(s.size)
    if n < 4 or s.std() == 0 or v.std() == 0:
        return (math.nan, math.nan, math.nan, n)
    r = float(np.corrcoef(s, v)[0, 1])
    z = math.atanh(max(min(r, 1 - 1e-12), -1 + 1e-12))
    half = norm.ppf(0.5 + confidence / 2) / math.sqrt(n - 3)
    return (r, math.tanh(z - half), math.tanh(z + half), n)


def collect(records) -> tuple[list[EpisodeRow], list[tuple], list[str]]:
    """Episode rows, shift rows (run, task, condition, level, seed, layer, js_bits, lift_change) and notes
    (runs left out) from run records (harness.analysis.runs.RunRecord)."""
    rows, notes, measures = [], [], {}
    for record in records:
        cond = run_condition(record.manifest)
        if cond is None:
            notes.append(f"{record.name}: several perturbations at once; left out of the robustness tables")
            continue
        for e in record.episodes:
            m = {}
            if e.ok and e.attention_path.is_file():
                controls = e.attention_path.with_name("controls.npz")
                try:
                    m = episode_measures(e.attention_path, controls if controls.is_file() else None)
                except (OSError, ValueError, KeyError) as exc:
                    notes.append(f"{record.name}/{e.task}/episode_{e.episode}: unreadable attention.npz ({exc})")
            measures[(record.name, e.task, e.seed)] = m
            rows.append(EpisodeRow(record.name, e.task, cond[0], cond[1], e.seed if e.seed is not None else -1, e.episode,
                                   e.status, bool(e.success), m.get("nuisance_mass", math.nan),
                                   m.get("target_lift", math.nan), m.get("distractor_mass", math.nan),
                                   m.get("background_mass", math.nan), m.get("nuisance_start", math.nan),
                                   m.get("nuisance_content", math.nan), m.get("target_lift_content", math.nan),
                                   m.get("nuisance_start_content", math.nan)))
    nominal = {(r.task, r.seed): r.run for r in rows if r.condition == "nominal"}
    shifts = []
    for r in rows:
        if r.condition == "nominal" or (r.task, r.seed) not in nominal:
            continue
        a = measures.get((nominal[(r.task, r.seed)], r.task, r.seed)) or {}
        b = measures.get((r.run, r.task, r.seed)) or {}
        if a.get("step0_rows") is None or b.get("step0_rows") is None or a["step0_rows"].shape != b["step0_rows"].shape:
            continue
        js = js_divergence_bits(a["step0_rows"], b["step0_rows"])
        lift = (b["step0_lift"] - a["step0_lift"]) if a.get("step0_lift") is not None and b.get("step0_lift") is not None \
            else np.full(js.shape, math.nan)
        for layer in range(js.shape[0]):
            shifts.append((r.run, r.task, r.condition, r.level, r.seed, layer, float(js[layer]), float(lift[layer])))
    return rows, shifts, notes


SUCCESS_COLUMNS = ("task", "condition", "level", "run", "n", "errored", "successes", "success_rate", "ci_low", "ci_high",
                   "nuisance_mass", "distractor_mass", "background_mass", "target_lift", "nuisance_content",
                   "target_lift_content")
SHIFT_COLUMNS = ("run", "task", "condition", "level", "seed", "layer", "js_bits", "lift_change")
ASSOCIATION_COLUMNS = ("task", "n", "point_biserial_r", "ci_low", "ci_high", "seed_ci_low", "seed_ci_high",
                       "mean_nuisance_success", "mean_nuisance_failure", "seeds", "start_point_biserial_r",
                       "start_seed_ci_low", "start_seed_ci_high", "within_point_biserial_r", "within_seed_ci_low",
                       "within_seed_ci_high", "map")


def _mean(values) -> float:
    v = np.asarray([x for x in values if math.isfinite(x)], np.float64)
    return float(v.mean()) if v.size else math.nan


def success_rows(rows: list[EpisodeRow]) -> list[tuple]:
    """Per task x condition x level (the nominal run repeated at level 0 of every condition): Wilson interval and
    mean episode measures."""
    conditions = sorted({r.condition for r in rows if r.condition != "nominal"})
    out = []
    for task in dict.fromkeys(r.task for r in rows):
        for condition in conditions or ["nominal"]:
            cells = sorted({(r.level, r.run) for r in rows if r.task == task and r.condition in (condition, "nominal")})
            for level, run in cells:
                cell = [r for r in rows if r.task == task and r.run == run]
                ok = [r for r in cell if r.status == "ok"]
                k = sum(r.success for r in ok)
                lo, hi = wilson_interval(k, len(ok)) if ok else (0.0, 1.0)
                out.append((task, condition, level, run, len(ok), len(cell) - len(ok), k,
                            k / len(ok) if ok else math.nan, lo, hi, _mean(r.nuisance_mass for r in ok),
                            _mean(r.distractor_mass for r in ok), _mean(r.background_mass for r in ok),
                            _mean(r.target_lift for r in ok), _mean(r.nuisance_content for r in ok),
                            _mean(r.target_lift_content for r in ok)))
    return out


def seed_cluster_interval(seeds, success, values, confidence: float = 0.95, resamples: int = CLUSTER_RESAMPLES,
                          seed: int = 0) -> tuple[float, float]:
    """Percentile interval of the point-biserial r when whole seeds (every episode of a seed, across conditions) are
    resampled with replacement; resamples where r is undefined (one class, constant values) are left out. nan with
    fewer than 4 seeds or fewer than MIN_CLASS successes or failures (a resample then hinges on a handful of
    episodes, and the percentile interval says little)."""
    seeds = np.asarray(seeds)
    s = np.asarray(success, np.float64)
    v = np.asarray(values, np.float64)
    keep = np.isfinite(s) & np.isfinite(v)
    seeds, s, v = seeds[keep], s[keep], v[keep]
    groups = [np.flatnonzero(seeds == k) for k in np.unique(seeds)]
    if len(groups) < 4 or min(int(s.sum()), int(s.size - s.sum())) < MIN_CLASS:
        return (math.nan, math.nan)
    rng = np.random.default_rng(seed)
    rs = []
    for draw in rng.integers(0, len(groups), size=(resamples, len(groups))):
        idx = np.concatenate([groups[g] for g in draw])
        a, b = s[idx], v[idx]
        if a.std() > 0 and b.std() > 0:
            rs.append(np.corrcoef(a, b)[0, 1])
    if len(rs) < resamples // 2:
        return (math.nan, math.nan)
    low, high = np.quantile(rs, [(1 - confidence) / 2, (1 + confidence) / 2])
    return (float(low), float(high))


def centred_per_run(rows: list[EpisodeRow], map_: str = "raw") -> list[float]:
    """Each episode's nuisance mass minus the mean of its run (one condition and level): what is left is the
    variation within a condition, which a perturbation that moves both nuisance mass and success cannot make."""
    means = {run: _mean(r.nuisance(map_)[0] for r in rows if r.run == run) for run in {r.run for r in rows}}
    return [r.nuisance(map_)[0] - means[r.run] for r in rows]


def has_content(rows: list[EpisodeRow]) -> bool:
    """Whether any episode has content-only measures (a run with a blank attention control)."""
    return any(math.isfinite(r.nuisance_content) for r in rows)


def has_reliance(rows: list[EpisodeRow]) -> bool:
    """Whether any episode has nuisance reliance (a run with --reliance-every)."""
    return any(math.isfinite(r.nuisance_reliance) for r in rows)


def association_rows(rows: list[EpisodeRow], maps: tuple[str, ...] | None = None) -> list[tuple]:
    """Per task and measure (ASSOCIATION_COLUMNS, `map`): the association of nuisance mass with success on the raw
    maps and, when `maps` holds "content" (default: when any episode has content-only measures), on the content-only
    maps; "reliance" (default: when any episode has it): the same for nuisance reliance."""
    maps = maps or ((MAPS if has_content(rows) else ("raw",)) + (("reliance",) if has_reliance(rows) else ()))
    out = []
    for task in dict.fromkeys(r.task for r in rows):
        ok = [r for r in rows if r.task == task and r.status == "ok"]
        for map_ in maps:
            success, seeds = [r.success for r in ok], [r.seed for r in ok]
            mass, start = [r.nuisance(map_)[0] for r in ok], [r.nuisance(map_)[1] for r in ok]
            within = centred_per_run(ok, map_)
            r_, lo, hi, n = point_biserial(success, mass)
            out.append((task, n, r_, lo, hi, *seed_cluster_interval(seeds, success, mass),
                        _mean(m for m, r in zip(mass, ok) if r.success), _mean(m for m, r in zip(mass, ok) if not r.success),
                        len({s for s, m in zip(seeds, mass) if math.isfinite(m)}), point_biserial(success, start)[0],
                        *seed_cluster_interval(seeds, success, start), point_biserial(success, within)[0],
                        *seed_cluster_interval(seeds, success, within), map_))
    return out


@dataclass(frozen=True)
class PairedCell:
    """One task x perturbed cell paired with the nominal episodes of the same seeds: a row of robustness_paired.csv
    (its columns are these fields, in this order)."""

    task: str
    condition: str
    level: int
    run: str
    pairs: int
    nominal_successes: int
    perturbed_successes: int
    nominal_only: int  # pairs the nominal run won and the perturbed lost
    perturbed_only: int
    difference: float  # perturbed - nominal success rate
    p_mcnemar: float
    p_holm: float  # Holm over the task's perturbed cells
    breaks: bool
    verdict: CellVerdict
    drop_upper: float  # upper confidence bound of the drop
    margin: float
    detectable_drop: float  # the smallest drop the test could declare (nan when none can be)
    cells: int

    def row(self) -> tuple:
        """The CSV row (PAIRED_COLUMNS)."""
        return astuple(self)


PAIRED_COLUMNS = tuple(f.name for f in fields(PairedCell))


def cell_verdict(counts: PairedCounts, p_holm: float, cells: int, alpha: float = ALPHA,
                 margin: float = MARGIN) -> CellVerdict:
    """BREAKS / HOLDS / UNDETERMINED of one perturbed cell (see the module docstring)."""
    if counts.n and p_holm <= alpha and counts.difference < 0:
        return CellVerdict.BREAKS
    if equivalent(counts, difference_interval(counts, 1.0 - alpha / max(cells, 1)), margin, alpha):
        return CellVerdict.HOLDS
    return CellVerdict.UNDETERMINED


def paired_rows(rows: list[EpisodeRow], alpha: float = ALPHA, margin: float = MARGIN) -> list[PairedCell]:
    """Per task x perturbed cell: the paired 2x2 against the nominal episodes of the same seeds, the exact McNemar p,
    its Holm adjustment over the task's perturbed cells, whether the cell breaks the task, its verdict (BREAKS,
    HOLDS, UNDETERMINED), the upper confidence bound of the drop, the margin, and the smallest drop the test could
    declare at its pairs and multiplicity (nan when none can be)."""
    out = []
    for task in dict.fromkeys(r.task for r in rows):
        nominal = {r.seed: r for r in rows if r.task == task and r.condition == "nominal" and r.status == "ok"}
        cells = sorted({(r.condition, r.level, r.run) for r in rows if r.task == task and r.condition != "nominal"})
        found = []
        for condition, level, run in cells:
            pairs = [(nominal[r.seed].success, r.success) for r in rows
                     if r.task == task and r.run == run and r.status == "ok" and r.seed in nominal]
            counts = PairedCounts.from_outcomes([a for a, _ in pairs], [b for _, b in pairs])
            found.append((condition, level, run, counts, mcnemar_exact(counts.baseline_only, counts.candidate_only)))
        adjusted = holm_adjust([f[4] for f in found])
        cells = len(found)
        for (condition, level, run, c, p), p_holm in zip(found, adjusted):
            verdict = cell_verdict(c, p_holm, cells, alpha, margin)
            low = difference_interval(c, 1.0 - alpha / max(cells, 1))[0] if c.n else -1.0
            loss = detectable_loss(c.n, alpha, cells)
            out.append(PairedCell(task, condition, level, run, c.n, c.baseline_successes, c.candidate_successes,
                                  c.baseline_only, c.candidate_only, c.difference, p, p_holm,
                                  verdict == CellVerdict.BREAKS, verdict, -low, margin,
                                  loss / c.n if loss is not None else math.nan, cells))
    return out


def verdict_line(task: str, success: list[tuple], paired: list[PairedCell] = ()) -> str:
    """A task's verdict in one short line (at most about 25 words): its nominal success, then the cells that break it
    (or that none does, and how many HOLD). The figures behind it are the cell table's (`paired` given), else the
    largest loss is named with its interval."""
    cells = [s for s in success if s[0] == task and math.isfinite(s[7])]
    nominal = next((s for s in cells if s[2] == 0), None)
    head = f"{task}: nominal {nominal[6]}/{nominal[4]}." if nominal else f"{task}: no nominal run to compare with."
    mine = [p for p in paired if p.task == task]
    if mine:
        broken = sorted((p for p in mine if p.breaks), key=lambda p: (p.condition, p.level))
        holds = sum(p.verdict == CellVerdict.HOLDS for p in mine)
        if broken and len(broken) == len(mine):
            tail = f"Breaks under every cell ({len(mine)})."
        elif broken:
            names = (", ".join(f"{p.condition} {p.level}" for p in broken) if len(broken) <= 3
                     else f"{len(broken)} of {len(mine)} cells")
            tail = (f"Breaks under {names}. Other cells: {holds} HOLD, {len(mine) - len(broken) - holds} "
                    f"{CellVerdict.UNDETERMINED}.")
        else:
            tail = f"No cell breaks it. Cells: {holds} HOLD, {len(mine) - holds} {CellVerdict.UNDETERMINED}."
        return f"{head} {tail}"
    worst = min((s for s in cells if s[2] > 0), key=lambda s: (s[7], -s[2]), default=None)
    if nominal is None:
        return head
    if worst is None:
        return f"{head} No perturbed run."
    if worst[7] >= nominal[7]:
        return f"{head} No perturbed cell does worse."
    return f"{head} Largest loss: {worst[1]} {worst[2]}, {worst[6]}/{worst[4]} (Wilson 95% [{worst[8]:.2f}, {worst[9]:.2f}])."


ASSOCIATION_HEADER = ("map", "measure", "over", "r with success", "seed-cluster 95%", "reads",
                      "detectable r (absolute)", "episodes", "seeds")
MAP_LABELS = {"raw": "raw", "content": "content only", "reliance": "reliance"}


def _reads(low: float, high: float) -> str:
    if not (math.isfinite(low) and math.isfinite(high)):
        return f"too few seeds, successes or failures (< {MIN_CLASS})"
    return "more goes with failure" if high < 0 else "more goes with success" if low > 0 else "no association shown"


def association_table(task: str, association: list[tuple]) -> list[tuple[str, ...]]:
    """A task's association rows as table cells (ASSOCIATION_HEADER): per map and scope (over episodes, within
    conditions, the first START_STEPS steps) the point-biserial r of nuisance mass (or reliance) with success, its
    seed-cluster interval, what it reads as, and the smallest |r| a null result could have told from 0
    (the detectable r column)."""
    out = []
    for a in (a for a in association if a[0] == task):
        map_ = a[16] if len(a) > 16 else "raw"
        measure = "nuisance reliance" if map_ == "reliance" else "nuisance mass"
        for scope, r_, low, high in (("episodes", a[2], a[5], a[6]), ("within conditions", a[13], a[14], a[15]),
                                     (f"first {START_STEPS} steps", a[10], a[11], a[12])):
            if not math.isfinite(r_):
                if scope == "episodes":
                    out.append((MAP_LABELS.get(map_, map_), measure, scope, "n/a", "-",
                                "too few episodes or no variation", "-", str(a[1]), str(a[9])))
                continue
            known = math.isfinite(low) and math.isfinite(high)
            null = known and low <= 0 <= high
            out.append((MAP_LABELS.get(map_, map_), measure, scope, f"{r_:+.2f}",
                        f"[{low:+.2f}, {high:+.2f}]" if known else "-", _reads(low, high),
                        f"{(high - low) / 2:.2f}" if null else "-", str(a[1]), str(a[9])))
    return out

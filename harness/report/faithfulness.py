"""The report's Faithfulness section: is the attention map telling the truth, open and closed loop?

Open loop: every finished episode's `faithfulness.jsonl` (runs made with `--faithfulness-every k`) is summarised
per run x task x camera x method: deletion and insertion AUC relative to the random map on the same steps
(harness.measures.faithfulness.relative_to_random: 1 = no better than random; deletion > 1 and insertion < 1
are better) with 95% bootstrap intervals over episodes, and top-k change over random-k change at each k; a heatmap
per task (methods x cameras, deletion ratio) and a short verdict line per task.

Closed loop (harness.report.closed_loop): runs given together whose protocols differ only in `policy.intervention`
(same model, tasks, seeds) are paired with the plain run, and each mask-top:K run with the mask-random:K run (is the
map better than chance at finding what the policy needs?): success of each arm (Wilson), the paired difference
(Newcombe's interval for paired proportions) and the exact McNemar p-value, per task.

Fills (harness.measures.faithfulness: mean, blur, impute) and orders: each open-loop row carries its fill and the
LeRF ratio beside deletion (MoRF) and insertion; runs of one task with different fills give a ranking-by-fill table
(`fill_ranking`). Per camera (`camera_rows`): the closed-loop arms of that camera (mask-all@CAMERA against the
plain run, mask-top:K:METHOD@CAMERA against mask-random:K@CAMERA) beside the open-loop ratio of the same method,
with a flag where they disagree, and a verdict line per camera (`camera_sentence`). `tables(runs)` -> {"faithfulness.csv", "interventions.csv", "faithfulness_cameras.csv"}; `section(runs, plots)` ->
HTML ("" when no run has either); `markdown(runs)` -> the same tables as Markdown (EVAL.md).
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

from harness.bounded import loads_json, read_jsonl_text
from harness.measures.attribution import display_rank
from harness.measures.faithfulness import relative_to_random
from harness.report import html as H
from harness.report.figures_file import markdown_table
from harness.report.closed_loop import INTERVENTION_COLUMNS, arm_name, intervention_rows, run_policy
from harness.report.rundata import csv_bytes as _csv
from harness.verdicts import Agreement  # agree, DISAGREE: open and closed loop on a camera's map

FAITH_COLUMNS = ("run", "task", "camera", "method", "steps", "episodes", "change_all_median",
                 "deletion_rel", "deletion_ci_low", "deletion_ci_high", "insertion_rel", "insertion_ci_low",
                 "insertion_ci_high", "top_over_random_k", "k", "fill", "lerf_rel", "lerf_ci_low", "lerf_ci_high",
                 "beats_random_from")
CAMERA_COLUMNS = ("task", "camera", "fill", "method", "open_loop_deletion", "open_ci_low", "open_ci_high",
                  "mask_all", "mask_all_difference", "mask_all_p", "mask_top", "top_vs_random_difference",
                  "top_vs_random_p", "agreement")


def read_rows(run) -> list[dict]:
    """Every faithfulness row of a run's finished episodes (RunData or RunRecord), with its episode."""
    record = getattr(run, "record", run)
    fill = (run_policy(run).get("faithfulness_fill") or "mean")
    rows = []
    for episode in record.episodes:
        path = episode.directory / "faithfulness.jsonl"
        if episode.ok and path.is_file():
            for number, line in enumerate(read_jsonl_text(path, errors="strict").splitlines(), 1):
                if line.strip():
                    row = loads_json(line, f"{path} line {number}")
                    row["task"], row["episode"] = episode.task, episode.episode
                    row.setdefault("fill", fill)
                    rows.append(row)
    return rows


def summarise(rows: list[dict], label: str, seed: int = 0) -> list[tuple]:
    """Rows of FAITH_COLUMNS (one per task x camera x method) from faithfulness rows."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for row in rows:
        groups[(row["task"], row["camera"], row["method"])].append(row)
    out = []
    for (task, camera, method), items in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], _order(kv[0][2]))):
        fills = sorted({r.get("fill", "mean") for r in items})
        episode = np.array([r["episode"] for r in items])
        value = lambda key: np.array([np.nan if r.get(key) is None else r[key] for r in items], float)  # noqa: E731
        dele = relative_to_random(value("deletion_auc"), value("random_deletion_auc"), episode, seed=seed)
        ins = relative_to_random(value("insertion_auc"), value("random_insertion_auc"), episode, seed=seed)
        ks = sorted({int(k.split("/")[1]) for r in items for k in r if k.startswith("top_k/")})
        k = ks[len(ks) // 2] if ks else None
        denominator = np.nansum(value(f"random_k/{k}")) if k else 0.0
        top = np.nansum(value(f"top_k/{k}")) / denominator if denominator > 0 else np.nan
        valid = np.isfinite(value("deletion_auc"))
        change = value("change_all")
        lerf = relative_to_random(value("lerf_auc"), value("random_lerf_auc"), episode, seed=seed)
        control = groups.get((task, camera, "random"), [])
        out.append((label, task, camera, method, int(valid.sum()), len(set(episode[valid].tolist())),
                    float(np.median(change[np.isfinite(change)])) if np.isfinite(change).any() else np.nan,
                    *dele[:3], *ins[:3], float(top), k, "+".join(fills), *lerf[:3], beats_random_from(items, control)))
    return out


def mean_curve(rows: list[dict], key: str = "deletion_curve") -> tuple[np.ndarray, np.ndarray] | None:
    """(fractions, mean curve over the rows with a finite AUC) of rows on one patch grid; None when none has one."""
    curves = [r[key] for r in rows if r.get(key) and r.get("deletion_auc") is not None
              and math.isfinite(r["deletion_auc"])]
    if not curves or len({len(c) for c in curves}) != 1:
        return None
    fractions = next(r["fractions"] for r in rows if r.get(key) and len(r[key]) == len(curves[0]))
    return np.asarray(fractions, float), np.mean(np.asarray(curves, float), axis=0)


def beats_random_from(rows: list[dict], control: list[dict], margin: float = 1.1) -> float:
    """The smallest deleted fraction k/n > 0 from which the method's mean deletion curve stays above `margin` x the
    random map's (the same steps) up to half the camera (beyond it every curve converges on the full deletion); NaN
    when it never does, or when either has no curve."""
    mine, theirs = mean_curve(rows), mean_curve(control)
    if mine is None or theirs is None or len(mine[1]) != len(theirs[1]):
        return float("nan")
    fractions, a = mine
    b = theirs[1]
    above = a > margin * b
    last = int(np.searchsorted(fractions, 0.5, side="right"))  # points with k/n <= 1/2
    for i in range(1, last):
        if above[i:last].all():
            return float(fractions[i])
    return float("nan")


def _order(method: str) -> tuple:
    base, _, layer = method.partition(":")
    return display_rank(base), int(layer) if layer.lstrip("-").isdigit() else 0


def _label(run) -> str:
    return getattr(run, "label", None) or getattr(run, "name", None) or getattr(getattr(run, "record", run), "name", "")


def open_rows(runs) -> list[tuple]:
    """FAITH_COLUMNS rows of every run."""
    return [r for run in runs for r in summarise(read_rows(run), _label(run))]


def _verdict(low: float, high: float) -> str:
    return "better" if math.isfinite(low) and low > 1 else "worse" if math.isfinite(high) and high < 1 else "random"


def camera_rows(runs, faith: list[tuple] | None = None) -> list[tuple]:
    """CAMERA_COLUMNS rows: each camera's closed-loop evidence (mask-all@CAMERA against the plain run;
    mask-top:K:METHOD@CAMERA against mask-random:K@CAMERA) beside the open-loop deletion ratio of the same method
    on the same task, per fill; `agreement` flags a camera where the two disagree. Only cameras with a closed-loop
    arm of their own (an intervention ending in @CAMERA)."""
    faith = open_rows(runs) if faith is None else faith
    specs = {arm_name(run): run_policy(run).get("intervention") or "" for run in runs}
    inter = [dict(zip(INTERVENTION_COLUMNS, r)) for r in intervention_rows(runs)]
    cameras = sorted({(r["task"], r["intervention"].partition("@")[2]) for r in inter if "@" in r["intervention"]})
    out = []
    for task, camera in cameras:
        mask_all = next((r for r in inter if r["task"] == task and r["intervention"] == f"mask-all@{camera}"
                         and not specs.get(r["baseline_run"])), None)
        tops = [r for r in inter if r["task"] == task and r["intervention"].startswith("mask-top:")
                and r["intervention"].endswith(f"@{camera}") and specs.get(r["baseline_run"], "").startswith("mask-random:")]
        needed = mask_all is not None and math.isfinite(mask_all["difference_ci_high"]) and mask_all["difference_ci_high"] < 0
        all_text = (f"{mask_all['baseline_successes']}/{mask_all['pairs']} -> {mask_all['successes']}/{mask_all['pairs']}"
                    if mask_all else "n/a")
        for top in tops or [None]:
            method = ":".join(top["intervention"].partition("@")[0].split(":")[2:]) if top else None
            closed = "n/a"
            if top is not None:
                closed = ("better" if top["difference"] < 0 and top["mcnemar_p"] < 0.05 else
                          "worse" if top["difference"] > 0 and top["mcnemar_p"] < 0.05 else "random")
            opens = [r for r in faith if r[1] == task and r[2] == camera and (r[3] == method if method else r[3] != "random")]
            if method is None and opens:  # no mask-top arm: the open loop's best method stands for the camera
                best = {}
                for r in opens:
                    if math.isfinite(r[7]) and (r[15] not in best or r[7] > best[r[15]][7]):
                        best[r[15]] = r
                opens = list(best.values())
            for r in opens or [None]:
                fill = r[15] if r else ""
                ratio, low, high = (r[7], r[8], r[9]) if r else (np.nan, np.nan, np.nan)
                opened = _verdict(low, high) if r else "n/a"
                if r is None or (closed == "n/a" and not needed):
                    agreement = "n/a"
                elif closed != "n/a" and closed != "random" and opened != "random":
                    agreement = Agreement.AGREE if closed == opened else Agreement.DISAGREE
                elif needed and opened == "worse":
                    agreement = f"{Agreement.DISAGREE} (camera needed; map below random open loop)"
                elif closed == "random" and opened == "random":
                    agreement = f"{Agreement.AGREE} (neither beats random)"
                else:
                    agreement = f"open loop {opened}, closed loop {closed}"
                out.append((task, camera, fill, r[3] if r else (method or ""), ratio, low, high, all_text,
                            mask_all["difference"] if mask_all else np.nan, mask_all["mcnemar_p"] if mask_all else np.nan,
                            top["intervention"] if top else "n/a", top["difference"] if top else np.nan,
                            top["mcnemar_p"] if top else np.nan, agreement))
    return out


def fill_ranking(faith: list[tuple]) -> list[tuple]:
    """How the ranking of methods changes with the fill: per (task, camera, method) the deletion ratio and rank
    (1 = highest) and the LeRF ratio under each fill, in rows (task, camera, method, {fill: (deletion, rank, lerf)}),
    with a last row per (task, camera) of method "spearman vs <first fill>" holding each fill's rank correlation
    with the first fill's ranking. Empty when no (task, camera) was measured with more than one fill."""
    from harness.analysis.sanity import spearman

    by: dict[tuple, dict[str, dict[str, tuple]]] = defaultdict(lambda: defaultdict(dict))
    for r in faith:
        if r[3] != "random" and math.isfinite(r[7]):
            by[(r[1], r[2])][r[15]][r[3]] = (r[7], r[16])
    out = []
    for (task, camera), fills in by.items():
        if len(fills) < 2:
            continue
        order = sorted(fills, key=lambda f: (f != "mean", f))
        methods = sorted({m for per in fills.values() for m in per}, key=_order)
        ranks = {}
        for fill in order:
            values = fills[fill]
            ranked = sorted(values, key=lambda m: -values[m][0])
            ranks[fill] = {m: ranked.index(m) + 1 for m in ranked}
        for m in methods:
            out.append((task, camera, m, {f: (*fills[f][m][:1], ranks[f][m], fills[f][m][1]) if m in fills[f] else
                                          (np.nan, None, np.nan) for f in order}))
        first = order[0]
        shared = [m for m in methods if all(m in fills[f] for f in order)]
        out.append((task, camera, f"spearman vs {first}",
                    {f: (spearman([ranks[first][m] for m in shared], [ranks[f][m] for m in shared])
                         if len(shared) > 2 else np.nan, None, np.nan) for f in order}))
    return out


CAMERA_FILL_HEADER = ("task", "camera", "fill", "methods", "deletion / random: range", "below random",
                      "above random", "earliest ordering above random", "from k/n")


def camera_fill_rows(task: str, camera: str, faith: list[tuple]) -> list[tuple[str, ...]]:
    """Per fill, the open loop over methods as table cells (CAMERA_FILL_HEADER): the range of deletion / random, how
    many methods lie below and above random by their intervals, and the ordering that first stays above random up to
    half the camera (k/n where it starts; '-' when none does)."""
    out = []
    rows = [r for r in faith if r[1] == task and r[2] == camera and r[3] != "random" and math.isfinite(r[7])]
    for fill in sorted({r[15] for r in rows}, key=lambda f: (f != "mean", f)):
        mine = [r for r in rows if r[15] == fill]
        ratios = [r[7] for r in mine]
        below = sum(1 for r in mine if _verdict(r[8], r[9]) == "worse")
        above = sum(1 for r in mine if _verdict(r[8], r[9]) == "better")
        starts = [r[19] for r in mine if math.isfinite(r[19])]
        best = min(starts) if starts else None
        out.append((task, camera, fill, str(len(mine)), f"{min(ratios):.2f}-{max(ratios):.2f}", str(below), str(above),
                    ", ".join(r[3] for r in mine if r[19] == best) if starts else "none up to half the camera",
                    f"{best:.2f}" if starts else "-"))
    return out


def camera_sentence(task: str, camera: str, faith: list[tuple], cams: list[tuple]) -> str:
    """A camera's verdict line (at most about 25 words): whether open and closed loop agree, and what masking the
    camera costs. The open loop's figures are camera_fill_rows', the closed loop's the camera table's."""
    text = f"{task}, {camera}: "
    mine = [c for c in cams if c[0] == task and c[1] == camera]
    if not mine:
        return text + ("open loop only (table below)." if camera_fill_rows(task, camera, faith) else "not measured.")
    flags = sorted({c[13] for c in mine if c[13].startswith(Agreement.DISAGREE)})
    text += f"open and closed loop {flags[0]}." if flags else "open and closed loop do not contradict each other."
    c = mine[0]
    if math.isfinite(c[8]):
        text += f" Masking the camera: {c[7]} (difference {c[8]:+.2f}, p = {c[9]:.3g})."
    return text


def tables(runs) -> dict[str, bytes]:
    """{"faithfulness.csv", "interventions.csv", "faithfulness_cameras.csv"} (header only when a run has none)."""
    faith = open_rows(runs)
    return {"faithfulness.csv": _csv(FAITH_COLUMNS, faith), "interventions.csv": _csv(INTERVENTION_COLUMNS, intervention_rows(runs)),
            "faithfulness_cameras.csv": _csv(CAMERA_COLUMNS, camera_rows(runs, faith))}


def sentence(task: str, rows: list[tuple]) -> str:
    """A verdict line of about 25 words at most: the method/layer/camera with the highest deletion ratio, whether it
    beats random, and the best raw attention layer's ratio; the other figures are the table's."""
    ranked = [r for r in rows if r[1] == task and r[3] != "random" and math.isfinite(r[7])]
    if not ranked:
        return f"{task}: no faithfulness measured."
    best = max(ranked, key=lambda r: r[7])
    _, _, camera, method, steps, episodes, _, d, dlo, dhi, i, ilo, ihi, *_ = best
    verdict = ("better than random" if math.isfinite(dlo) and dlo > 1 else
               "worse than random" if math.isfinite(dhi) and dhi < 1 else "not distinguishable from random")
    if episodes < MIN_EPISODES:
        verdict = f"with no verdict against random ({TOO_FEW})"
    attention = [r for r in ranked if r[3].startswith("attention:") and r[2] == camera]
    tail = ""
    if attention and best not in attention:
        a = max(attention, key=lambda r: r[7])
        tail = f" Best raw attention layer: {a[3].split(':')[1]}, {a[7]:.2f}x random [{a[8]:.2f}, {a[9]:.2f}]."
    # a verdict line (issue 67 item 4); insertion AUC and steps are in the table row of the same method
    return (f"{task}, {camera}: {_name(method)} ranks best, {verdict} (deletion AUC "
            f"{_ci_text(d, dlo, dhi, episodes).replace(' ', 'x random ', 1)}, {episodes} episodes).{tail}")


def _name(method: str) -> str:
    base, _, layer = method.partition(":")
    return f"layer {layer} attention" if base == "attention" else base


def heatmap(task: str, rows: list[tuple]) -> bytes:
    """PNG: methods (rows) x cameras (columns) of the deletion ratio (1 = random; colours clipped to 0.5..1.5)."""
    return figure([(task, rows)])


def figure(panels: list[tuple[str, list[tuple]]]) -> bytes:
    """PNG of one heatmap per (task, rows) side by side, one colour bar (deletion AUC / random, >1 better)."""
    from harness.report.figures import deletion_heatmaps

    methods = sorted({r[3] for task, rows in panels for r in rows if r[1] == task}, key=_order)  # every panel's rows
    cells = [(task, {(r[3], r[2]): r[7] for r in rows if r[1] == task}) for task, rows in panels]
    return deletion_heatmaps(cells, methods)


def section(runs, plots) -> str:
    """The page's Faithfulness section ("" when no run measured faithfulness or ran an intervention)."""
    body = []
    for run in runs:
        rows = summarise(read_rows(run), run.label)
        if not rows:
            continue
        body.append(H.section(f"Open loop: {run.label}", "", level=3))
        for task in dict.fromkeys(r[1] for r in rows):
            body.append(H.Raw(f"<p>{H.esc(sentence(task, rows))}</p>"))
            body.append(plots.add(f"faithfulness_{H.anchor_id(task)[2:]}_{run.label}", heatmap(task, rows),
                                  f"faithfulness {task}", "Deletion AUC relative to the random map per method and "
                                  "camera (1 = random; higher: deleting the patches the map ranks first moves the "
                                  "action sooner)."))
            body.append(H.table(("camera", "method", "fill", "steps", "episodes", "deletion (MoRF) / random [95%]",
                                 "insertion / random [95%]", "LeRF / random [95%]", "top-k / random-k (k)"),
                                [(r[2], r[3], r[15], r[4], r[5], *(H.fmt_ci(v, lo, hi, 2) if r[5] >= MIN_EPISODES
                                                                   else _ci_text(v, lo, hi, r[5])
                                                                   for v, lo, hi in (r[7:10], r[10:13], r[16:19])),
                                  f"{r[13]:.2f} ({r[14]})" if math.isfinite(r[13]) else "n/a")
                                 for r in rows if r[1] == task], numeric=(3, 4)))
    faith = open_rows(runs)
    ranking_rows = fill_ranking(faith)
    if ranking_rows:
        fills = list(ranking_rows[0][3])
        body.append(H.section("Ranking of methods by fill", "", level=3))
        body.append(H.note("Deletion (MoRF) AUC / random and the method's rank (1 = highest) under each fill, LeRF / random "
                           "beside it (lower is better); the last row per camera: Spearman correlation of each fill's "
                           "ranking with the first fill's."))
        body.append(H.table(("task", "camera", "method", *[f"{f}: deletion (rank), LeRF" for f in fills]),
                            [(t, c, m, *[_rank_cell(v) for v in by.values()]) for t, c, m, by in ranking_rows]))
    cams = camera_rows(runs, faith)
    if cams:
        body.append(H.section("Per camera: open loop beside closed loop", "", level=3))
        for task, camera in dict.fromkeys((c[0], c[1]) for c in cams):
            body.append(H.Raw(f"<p>{H.esc(camera_sentence(task, camera, faith, cams))}</p>"))
        fills = [row for task, camera in dict.fromkeys((c[0], c[1]) for c in cams)
                 for row in camera_fill_rows(task, camera, faith)]
        if fills:
            body.append(H.table(CAMERA_FILL_HEADER, fills, numeric=(3, 5, 6)))
        body.append(H.table(("task", "camera", "fill", "method", "open loop: deletion / random [95%]",
                             "mask-all@camera (plain -> masked)", "difference (p)", "mask-top vs mask-random",
                             "difference (p)", "open vs closed loop"),
                            [(c[0], c[1], c[2], c[3], H.fmt_ci(c[4], c[5], c[6], 2), c[7], _diff_cell(c[8], c[9]),
                              c[10], _diff_cell(c[11], c[12]), c[13]) for c in cams]))
    inter = intervention_rows(runs)
    if inter:
        body.append(H.section("Closed loop: interventions", "", level=3))
        body.append(H.table(("intervention", "against", "task", "pairs", "against: success [Wilson]", "with intervention",
                             "difference [Newcombe]", "McNemar p"),
                            [(r[2], r[1], r[3], r[4], H.fmt_ci(r[6], r[7], r[8], 2), H.fmt_ci(r[10], r[11], r[12], 2),
                              H.fmt_ci(r[13], r[14], r[15], 2), f"{r[16]:.3g}") for r in inter], numeric=(3,)))
    if not body:
        return ""
    intro = H.note("Is the attention map telling the truth? Open loop: patches are deleted (the run's fill: mean, blur "
                   "or impute) in the order each method ranks them and the predicted chunk's change is measured (same "
                   "rng); AUCs are divided by the random map's on the same steps, so 1 = no better than random "
                   "(deletion, most relevant first: higher is better; insertion and LeRF, least relevant first: lower "
                   "is better). Closed loop: runs with --intervene against the plain run on the same seeds; per camera, "
                   "both side by side, with a flag where they disagree.")
    return H.section("Faithfulness", intro + "".join(str(b) for b in body), anchor="faithfulness")


def _rank_cell(value: tuple) -> str:
    ratio, rank, lerf = value
    if not math.isfinite(ratio):
        return "n/a"
    if rank is None:
        return f"{ratio:.2f}"
    return f"{ratio:.2f} ({rank})" + (f", {lerf:.2f}" if math.isfinite(lerf) else "")


def _diff_cell(difference: float, p: float) -> str:
    return "n/a" if not math.isfinite(difference) else f"{difference:+.2f} (p = {p:.3g})"


MIN_EPISODES = 4  # a bootstrap over fewer episodes collapses (2 episodes: at most 3 distinct resamples)
TOO_FEW = "too few episodes for an interval"


def _ci_text(value: float, low: float, high: float, episodes: int) -> str:
    """"1.23 [1.01, 1.40]", or "1.23 (too few episodes for an interval)" from fewer than MIN_EPISODES episodes."""
    if episodes < MIN_EPISODES:
        return f"{value:.2f} ({TOO_FEW})"
    return f"{value:.2f} [{low:.2f}, {high:.2f}]"


def markdown(runs) -> str:
    """The open-loop table and the intervention table as Markdown (EVAL.md), plus the sentences."""
    lines = []
    for run in runs:
        rows = summarise(read_rows(run), getattr(run, "label", getattr(run, "name", "")))
        if not rows:
            continue
        lines += ["| task | camera | method | fill | steps | deletion (MoRF) AUC / random [95%] | insertion AUC / random "
                  "[95%] | LeRF AUC / random [95%] | top-k / random-k (k) |", "|---|---|---|---|---:|---|---|---|---|"]
        for r in rows:
            top = f"{r[13]:.2f} ({r[14]})" if math.isfinite(r[13]) else "n/a"
            lines.append(f"| {r[1]} | {r[2]} | {r[3]} | {r[15]} | {r[4]} | {_ci_text(r[7], r[8], r[9], r[5])} | "
                         f"{_ci_text(r[10], r[11], r[12], r[5])} | {_ci_text(r[16], r[17], r[18], r[5])} | {top} |")
        lines.append("")
        for task in dict.fromkeys(r[1] for r in rows):
            lines.append(f"- {sentence(task, rows)}")
        lines.append("")
    faith = open_rows(runs)
    ranking_rows = fill_ranking(faith)
    if ranking_rows:
        fills = list(ranking_rows[0][3])
        lines += ["Ranking of methods by fill: deletion (MoRF) AUC / random (rank, 1 = highest), LeRF AUC / random.", "",
                  "| task | camera | method | " + " | ".join(fills) + " |", "|---|---|---|" + "---|" * len(fills)]
        for t, c, m, by in ranking_rows:
            lines.append(f"| {t} | {c} | {m} | " + " | ".join(_rank_cell(v) for v in by.values()) + " |")
        lines.append("")
    cams = camera_rows(runs, faith)
    if cams:
        lines += ["| task | camera | fill | method | open loop: deletion / random [95%] | mask-all@camera | difference (p) "
                  "| mask-top vs mask-random | difference (p) | open vs closed loop |", "|---|---|---|---|---|---|---|---|---|---|"]
        for c in cams:
            lines.append(f"| {c[0]} | {c[1]} | {c[2]} | {c[3]} | {c[4]:.2f} [{c[5]:.2f}, {c[6]:.2f}] | {c[7]} | "
                         f"{_diff_cell(c[8], c[9])} | `{c[10]}` | {_diff_cell(c[11], c[12])} | {c[13]} |")
        lines.append("")
        for task, camera in dict.fromkeys((c[0], c[1]) for c in cams):
            lines.append(f"- {camera_sentence(task, camera, faith, cams)}")
        lines.append("")
        fills = [row for task, camera in dict.fromkeys((c[0], c[1]) for c in cams)
                 for row in camera_fill_rows(task, camera, faith)]
        if fills:
            lines += ["Open loop per camera and fill, over methods:", "", *markdown_table(CAMERA_FILL_HEADER, fills), ""]
    inter = intervention_rows(runs)
    if inter:
        lines += ["| task | intervention | against | pairs | against: success [Wilson] | with intervention [Wilson] | "
                  "difference [Newcombe] | McNemar p |", "|---|---|---|---:|---|---|---|---|"]
        for r in inter:
            lines.append(f"| {r[3]} | `{r[2]}` | {r[1]} | {r[4]} | {r[5]}/{r[4]} = {r[6]:.2f} [{r[7]:.2f}, {r[8]:.2f}] | "
                         f"{r[9]}/{r[4]} = {r[10]:.2f} [{r[11]:.2f}, {r[12]:.2f}] | {r[13]:+.2f} [{r[14]:+.2f}, "
                         f"{r[15]:+.2f}] | {r[16]:.3g} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    """`python -m harness.report.faithfulness RUN... [--eval-md EVAL.md] [--figure PNG]`: the Faithfulness section
    (harness.report.eval_md); --figure PNG also draws the deletion-ratio heatmaps of every task."""
    import argparse

    from harness.report.eval_md import section_main, tables_section

    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--figure", default=None)
    known, rest = parser.parse_known_args(argv)

    def body(records) -> str:
        rows = [r for record in records for r in summarise(read_rows(record), record.name)]
        if known.figure and rows:
            with open(known.figure, "wb") as f:
                f.write(figure([(task, rows) for task in dict.fromkeys(r[1] for r in rows)]))
        return markdown(records)

    empty = "no run here has faithfulness or intervention rows: give runs made with --faithfulness-every or --intervene"
    return section_main(rest, "python -m harness.report.faithfulness", "Write the Faithfulness section of an EVAL.md "
                        "(--figure PNG: also the deletion-ratio heatmaps of every task).",
                        tables_section("## Faithfulness", body, empty),
                        options=("--figure", known.figure) if known.figure else ())


if __name__ == "__main__":
    raise SystemExit(main())

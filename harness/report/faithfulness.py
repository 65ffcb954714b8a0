"""The report's Faithfulness section: is the attention map telling the truth, open and closed loop?

Open loop: every finished episode's `faithfulness.jsonl` (runs made with `--faithfulness-every k`) is summarised
per run x task x camera x method: deletion and insertion AUC relative to the random map on the same steps
(harness.analysis.faithfulness.relative_to_random: 1 = no better than random; deletion > 1 and insertion < 1
are better) with 95% bootstrap intervals over episodes, and top-k change over random-k change at each k. A
heatmap per task (methods x cameras, deletion ratio) and one plain sentence per task.

Closed loop: runs given together whose protocols differ only in `policy.intervention` (same model, tasks,
seeds) are paired with the plain run, and each mask-top:K run with the mask-random:K run (is the map better than
chance at finding what the policy needs?): success of each arm (Wilson), the paired difference (Newcombe's interval
for paired proportions) and the exact McNemar p-value, per task.

`tables(runs)` -> {"faithfulness.csv", "interventions.csv"}; `section(runs, plots)` -> HTML ("" when no run
has either); `markdown(runs)` -> the same tables as Markdown (EVAL.md).
"""

from __future__ import annotations

import io
import json
import math
from collections import defaultdict

import numpy as np

from harness.analysis.faithfulness import relative_to_random
from harness.analysis.paired import PairedCounts, mcnemar_exact, newcombe_paired_interval
from harness.analysis.stats import wilson_interval
from harness.report import html as H

FAITH_COLUMNS = ("run", "task", "camera", "method", "steps", "episodes", "change_all_median",
                 "deletion_rel", "deletion_ci_low", "deletion_ci_high", "insertion_rel", "insertion_ci_low",
                 "insertion_ci_high", "top_over_random_k", "k")
INTERVENTION_COLUMNS = ("run", "baseline_run", "intervention", "task", "pairs", "baseline_successes", "baseline_rate",
                        "baseline_ci_low", "baseline_ci_high", "successes", "rate", "ci_low", "ci_high",
                        "difference", "difference_ci_low", "difference_ci_high", "mcnemar_p")


def read_rows(run) -> list[dict]:
    """Every faithfulness row of a run's finished episodes (RunData or RunRecord), with its episode."""
    record = getattr(run, "record", run)
    rows = []
    for episode in record.episodes:
        path = episode.directory / "faithfulness.jsonl"
        if episode.ok and path.is_file():
            for line in path.read_text().splitlines():
                if line.strip():
                    row = json.loads(line)
                    row["task"], row["episode"] = episode.task, episode.episode
                    rows.append(row)
    return rows


def summarise(rows: list[dict], label: str, seed: int = 0) -> list[tuple]:
    """Rows of FAITH_COLUMNS (one per task x camera x method) from faithfulness rows."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for row in rows:
        groups[(row["task"], row["camera"], row["method"])].append(row)
    out = []
    for (task, camera, method), items in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], _order(kv[0][2]))):
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
        out.append((label, task, camera, method, int(valid.sum()), len(set(episode[valid].tolist())),
                    float(np.median(change[np.isfinite(change)])) if np.isfinite(change).any() else np.nan,
                    *dele[:3], *ins[:3], float(top), k))
    return out


def _order(method: str) -> tuple:
    base, _, layer = method.partition(":")
    rank = {"attention": 0, "rollout": 1, "grad-attention": 2, "saliency": 3, "random": 4}.get(base, 5)
    return rank, int(layer) if layer.lstrip("-").isdigit() else 0


def _policy(run) -> dict:
    record = getattr(run, "record", run)
    return dict((record.manifest.get("protocol") or {}).get("policy") or {})


def _arm_key(run) -> tuple:
    """What must agree for two runs to be arms of one intervention experiment (all but the intervention)."""
    record = getattr(run, "record", run)
    protocol = dict(record.manifest.get("protocol") or {})
    policy = {k: v for k, v in (protocol.get("policy") or {}).items()
              if k not in ("intervention", "attribution", "faithfulness_every", "faithfulness_fill")}
    return json.dumps({"model_fingerprint": protocol.get("model_fingerprint"), "max_steps": protocol.get("max_steps"),
                       "env": protocol.get("env"), "policy": policy}, sort_keys=True)


def intervention_rows(runs) -> list[tuple]:
    """Rows of INTERVENTION_COLUMNS: each run with an intervention against the plain run of the same experiment,
    and each mask-top:K run against the mask-random:K run of the same experiment (is the map better than chance?).
    When an intervention was run on several tasks (one run per task or one run of several), a "pooled" row per
    (intervention, comparison) pools its pairs over the tasks (task "pooled", run and baseline_run joined by '+')."""
    plain, random_k = {}, {}  # (experiment, task) -> the run holding that task
    for run in runs:
        spec = _policy(run).get("intervention")
        for task in getattr(run, "record", run).tasks:
            if not spec:
                plain.setdefault((_arm_key(run), task), run)
            elif spec.startswith("mask-random:"):
                random_k.setdefault((_arm_key(run), _masked_count(spec), task), run)
    out, pooled = [], {}
    for run in runs:
        spec = _policy(run).get("intervention")
        if not spec:
            continue
        for task in getattr(run, "record", run).tasks:
            bases = [("plain", plain.get((_arm_key(run), task)))]
            if spec.startswith("mask-top:"):
                bases.append((f"mask-random:{_masked_count(spec)[0]}",
                              random_k.get((_arm_key(run), _masked_count(spec), task))))
            for kind, base in bases:
                if base is None:
                    continue
                for _, b, c in _paired_outcomes(base, run, task):
                    out.append(_row(_name_of(run), _name_of(base), spec, task, b, c))
                    entry = pooled.setdefault((spec, kind), ([], [], [], [], set()))
                    entry[0].append(_name_of(run))
                    entry[1].append(_name_of(base))
                    entry[2].extend(b)
                    entry[3].extend(c)
                    entry[4].add(task)
    for (spec, _), (names, base_names, b, c, tasks) in pooled.items():
        if len(tasks) > 1:
            out.append(_row("+".join(dict.fromkeys(names)), "+".join(dict.fromkeys(base_names)), spec, "pooled", b, c))
    return out


def _name_of(run) -> str:
    return getattr(run, "label", None) or getattr(run, "record", run).name


def _masked_count(spec: str) -> tuple[str, str]:
    """(K, camera) of a mask spec: mask-top:4:attention:2@image_wrist -> ("4", "image_wrist")."""
    body, _, camera = spec.partition("@")
    return body.split(":")[1], camera


def _paired_outcomes(base, run, task: str) -> list[tuple[str, list[bool], list[bool]]]:
    """[(task, baseline successes, run successes)] over the task's seeds both runs finished without error ([] if none)."""
    b_eps = {e.seed: e for e in getattr(base, "record", base).episodes if e.ok and e.task == task}
    c_eps = {e.seed: e for e in getattr(run, "record", run).episodes if e.ok and e.task == task}
    seeds = sorted(set(b_eps) & set(c_eps))
    if not seeds:
        return []
    return [(task, [bool(b_eps[s].success) for s in seeds], [bool(c_eps[s].success) for s in seeds])]


def _row(name: str, base_name: str, spec: str, task: str, b: list[bool], c: list[bool]) -> tuple:
    counts = PairedCounts.from_outcomes(b, c)
    n = len(b)
    lo, hi = newcombe_paired_interval(counts.both, counts.candidate_only, counts.baseline_only, counts.neither)
    return (name, base_name, spec, task, n, sum(b), sum(b) / n, *wilson_interval(sum(b), n), sum(c), sum(c) / n,
            *wilson_interval(sum(c), n), (sum(c) - sum(b)) / n, lo, hi,
            mcnemar_exact(counts.baseline_only, counts.candidate_only))


def _csv(columns, rows) -> bytes:
    import csv

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow(["" if isinstance(v, float) and not math.isfinite(v) else (f"{v:.6g}" if isinstance(v, float) else v)
                         for v in row])
    return buffer.getvalue().encode()


def tables(runs) -> dict[str, bytes]:
    """{"faithfulness.csv", "interventions.csv"} (header only when a run has none)."""
    faith = [r for run in runs for r in summarise(read_rows(run), getattr(run, "label", getattr(run, "name", "")))]
    return {"faithfulness.csv": _csv(FAITH_COLUMNS, faith), "interventions.csv": _csv(INTERVENTION_COLUMNS, intervention_rows(runs))}


def sentence(task: str, rows: list[tuple]) -> str:
    """One plain sentence: the method/layer/camera with the highest deletion ratio, and whether it beats random."""
    ranked = [r for r in rows if r[1] == task and r[3] != "random" and math.isfinite(r[7])]
    if not ranked:
        return f"{task}: no faithfulness measured."
    best = max(ranked, key=lambda r: r[7])
    _, _, camera, method, steps, episodes, _, d, dlo, dhi, i, ilo, ihi, *_ = best
    verdict = ("better than random" if math.isfinite(dlo) and dlo > 1 else
               "worse than random" if math.isfinite(dhi) and dhi < 1 else "not distinguishable from random")
    attention = [r for r in ranked if r[3].startswith("attention:") and r[2] == camera]
    tail = ""
    if attention and best not in attention:
        a = max(attention, key=lambda r: r[7])
        tail = (f"; the best raw attention layer ({a[3].split(':')[1]}) reaches {a[7]:.2f} "
                f"[{a[8]:.2f}, {a[9]:.2f}]")
    return (f"{task}, {camera}: {_name(method)} ranks the patches the action depends on {verdict}: deletion AUC "
            f"{d:.2f}x random [{dlo:.2f}, {dhi:.2f}], insertion AUC {i:.2f}x random [{ilo:.2f}, {ihi:.2f}] "
            f"({steps} steps, {episodes} episodes){tail}.")


def _name(method: str) -> str:
    base, _, layer = method.partition(":")
    return f"layer {layer} attention" if base == "attention" else base


def _draw(ax, task: str, rows: list[tuple], methods: list[str]):
    """methods (rows) x cameras (columns) of the deletion ratio on `ax` (n/a where absent); returns the image artist."""
    from matplotlib.colors import TwoSlopeNorm

    items = [r for r in rows if r[1] == task]
    cameras = sorted({r[2] for r in items})
    grid = np.full((len(methods), len(cameras)), np.nan)
    for r in items:
        grid[methods.index(r[3]), cameras.index(r[2])] = r[7]
    im = ax.imshow(np.ma.masked_invalid(grid), cmap="RdBu_r", norm=TwoSlopeNorm(1.0, 0.5, 1.5), aspect="auto")
    for (y, x), v in np.ndenumerate(grid):
        ax.text(x, y, "n/a" if not np.isfinite(v) else f"{v:.2f}", ha="center", va="center", fontsize=8)
    ax.set_xticks(range(len(cameras)), [c.removeprefix("image_") for c in cameras])
    ax.set_yticks(range(len(methods)), methods)
    ax.set_title(task, fontsize=9)
    return im


def heatmap(task: str, rows: list[tuple]) -> bytes:
    """PNG: methods (rows) x cameras (columns) of the deletion ratio (1 = random; colours clipped to 0.5..1.5)."""
    return figure([(task, rows)])


def figure(panels: list[tuple[str, list[tuple]]]) -> bytes:
    """PNG of one heatmap per (task, rows) side by side, one colour bar (deletion AUC / random, >1 better)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = sorted({r[3] for task, rows in panels for r in rows if r[1] == task}, key=_order)  # every panel's rows
    height = len(methods)
    fig, axes = plt.subplots(1, len(panels), figsize=(1.4 + 2.2 * len(panels), 1.2 + 0.34 * height), dpi=110,
                             squeeze=False)
    im = None
    for i, (ax, (task, rows)) in enumerate(zip(axes[0], panels)):
        im = _draw(ax, task, rows, methods)
        if i:  # the same rows in every panel: labelled once, on the left
            ax.tick_params(labelleft=False)
    fig.suptitle("deletion AUC / random map's (1 = random, > 1: deleting the top-ranked patches moves the action sooner)",
                 fontsize=8)
    fig.colorbar(im, ax=list(axes[0]), fraction=0.03)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


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
            body.append(H.table(("camera", "method", "steps", "episodes", "deletion / random [95%]",
                                 "insertion / random [95%]", "top-k / random-k (k)"),
                                [(r[2], r[3], r[4], r[5], H.fmt_ci(r[7], r[8], r[9], 2), H.fmt_ci(r[10], r[11], r[12], 2),
                                  f"{r[13]:.2f} ({r[14]})" if math.isfinite(r[13]) else "n/a")
                                 for r in rows if r[1] == task], numeric=(2, 3)))
    inter = intervention_rows(runs)
    if inter:
        body.append(H.section("Closed loop: interventions", "", level=3))
        body.append(H.table(("intervention", "against", "task", "pairs", "against: success [Wilson]", "with intervention",
                             "difference [Newcombe]", "McNemar p"),
                            [(r[2], r[1], r[3], r[4], H.fmt_ci(r[6], r[7], r[8], 2), H.fmt_ci(r[10], r[11], r[12], 2),
                              H.fmt_ci(r[13], r[14], r[15], 2), f"{r[16]:.3g}") for r in inter], numeric=(3,)))
    if not body:
        return ""
    intro = H.note("Is the attention map telling the truth? Open loop: patches are deleted (mean fill) in the order "
                   "each method ranks them and the predicted chunk's change is measured (same rng); AUCs are divided by "
                   "the random map's on the same steps, so 1 = no better than random (deletion: higher is better; "
                   "insertion: lower is better). Closed loop: runs with --intervene against the plain run on the same "
                   "seeds.")
    return H.section("Faithfulness", intro + "".join(str(b) for b in body), anchor="faithfulness")


def markdown(runs) -> str:
    """The open-loop table and the intervention table as Markdown (EVAL.md), plus the sentences."""
    lines = []
    for run in runs:
        rows = summarise(read_rows(run), getattr(run, "label", getattr(run, "name", "")))
        if not rows:
            continue
        lines += ["| task | camera | method | steps | deletion AUC / random [95%] | insertion AUC / random [95%] | "
                  "top-k / random-k (k) |", "|---|---|---|---:|---|---|---|"]
        for r in rows:
            top = f"{r[13]:.2f} ({r[14]})" if math.isfinite(r[13]) else "n/a"
            lines.append(f"| {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[7]:.2f} [{r[8]:.2f}, {r[9]:.2f}] | "
                         f"{r[10]:.2f} [{r[11]:.2f}, {r[12]:.2f}] | {top} |")
        lines.append("")
        for task in dict.fromkeys(r[1] for r in rows):
            lines.append(f"- {sentence(task, rows)}")
        lines.append("")
    inter = intervention_rows(runs)
    if inter:
        lines += ["| task | intervention | against | pairs | against: success [Wilson] | with intervention [Wilson] | "
                  "difference [Newcombe] | McNemar p |", "|---|---|---|---:|---|---|---|---|"]
        for r in inter:
            lines.append(f"| {r[3]} | `{r[2]}` | {r[1]} | {r[4]} | {r[5]}/{r[4]} = {r[6]:.2f} [{r[7]:.2f}, {r[8]:.2f}] | "
                         f"{r[9]}/{r[4]} = {r[10]:.2f} [{r[11]:.2f}, {r[12]:.2f}] | {r[13]:+.2f} [{r[14]:+.2f}, "
                         f"{r[15]:+.2f}] | {r[16]:.3g} |")
    return "\n".join(lines)


if __name__ == "__main__":  # python -m harness.report.faithfulness RUN... [--figure PNG]: the Markdown tables
    import argparse

    from harness.analysis.runs import load_run

    parser = argparse.ArgumentParser(prog="python -m harness.report.faithfulness")
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--figure", default=None, help="also write the deletion-ratio heatmaps of every task here")
    args = parser.parse_args()
    records = [load_run(p) for p in args.runs]
    print(markdown(records))
    if args.figure:
        rows = [r for record in records for r in summarise(read_rows(record), record.name)]
        tasks = list(dict.fromkeys(r[1] for r in rows))
        with open(args.figure, "wb") as f:
            f.write(figure([(task, rows) for task in tasks]))

"""report.html: the page's sections (status banners, cross-task comparison, one section per task, run manifests,
definitions) from analysed runs. Figures come from harness.report.figures, building blocks from harness.report.html;
`render` returns the document and the PNG files of its figures."""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from harness.analysis.runs import no_attention_line
from harness.report import figures
from harness.report import html as H
from harness.report.rundata import RunData, episode_headline, representative, share_categories
from harness.report.sections import sections

SHARE_COLOURS = {"primary": "#4c72b0", "wrist": "#55a868", "language": "#c44e52", "readout": "#8172b2",
                 "lowdim": "#ccb974", "proprio": "#ccb974", "other": "#999999", "earlier timesteps": "#64b5cd"}


def render(runs: list[RunData], tasks: list[str], out: Path, overlays: dict[tuple[str, str], Future],
           summaries: dict | None = None) -> tuple[str, dict[str, bytes]]:
    """(report.html text, {plot file name: PNG bytes}); `out` is the report folder (videos are linked relative to it),
    overlays: (run label, task) -> future of (PNG, caption) or None; summaries: {section anchor: what the section's
    `summarise` made} (harness.report.sections; a section computes what it needs when its entry is missing)."""
    summaries = summaries or {}
    plots = _Plots()
    body = [_status_banners(runs), H.Raw("<p class='note'>Every number here comes from the CSV files in "
                                         "<code>tables/</code> next to this page; intervals are 95% (Wilson for success, "
                                         "percentile bootstrap over episodes for attention).</p>")]
    body.append(_cross_task(runs, tasks, plots))
    for task in tasks:
        body.append(_task_section(runs, task, out, plots, overlays))
    present = []
    for section in sections():  # each "" unless the runs hold what it reads
        html_ = section.section(runs, plots, summaries.get(section.anchor))
        body.append(html_)
        if html_:
            present.append((section.anchor, section.name))
    body.append(H.section("Run manifest", "".join(_manifest_section(run) for run in runs), anchor="manifest"))
    body.append(H.section("Definitions", H.Raw(_DEFINITIONS), anchor="definitions"))
    toc = [("cross-task", "Cross-task comparison")] + [(H.anchor_id("task-" + t), t) for t in tasks] + [
        ("manifest", "Run manifest"), ("definitions", "Definitions")]
    for entry in present:
        toc.insert(-2, entry)
    title = "Attention report: " + " vs ".join(run.label for run in runs)
    subtitle = (f"{len(runs)} run(s), {len(tasks)} task(s), {sum(len(r.summaries) for r in runs)} episodes analysed; "
                f"generated {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    return H.page(title, "".join(body), subtitle, toc, footer="octo-harness report"), plots.files


def _mask_metric(run: RunData, name: str) -> str | None:
    """mask_lift / mask_mass metric of a mask name on the headline camera."""
    if run.headline is None:
        return None
    return run.headline.replace("/target", f"/{name}")


def _task_table(runs: list[RunData], task: str) -> str:
    header = ["run", "episodes done / jobs", "missing", "errored", "success (95% Wilson)",
              "target lift, last layer", "robot mass, last layer", "entropy, last layer (nats)"]
    rows, without = [], []
    for run in runs:
        s = run.success.get(task)
        if s is None:  # a run of other tasks: named below the table, not a row of empty cells
            without.append(run.label)
            continue
        done = s["jobs"] - s["missing"]
        rate = (H.fmt_ci(s["success_rate"], s["ci_low"], s["ci_high"]) if s["n"] else H.absent("no finished episode"))
        cells = [H.swatch(run.colour, run.label), f"{done} / {s['jobs']}", s["missing"], s["errored"],
                 H.Raw(f"{s['successes']}/{s['n']} = {rate}") if s["n"] else rate]
        for metric in (run.headline, _mask_metric(run, "robot").replace("mask_lift", "mask_mass") if run.headline else None,
                       "entropy"):
            found = run.layer_values(task, metric) if metric else None
            if not run.record.attention:
                cells.append(H.absent("no attention"))
            elif found is None:
                cells.append(H.absent("absent (no mask)" if metric != "entropy" else "n/a"))
            else:
                v, lo, hi = found
                cells.append(H.fmt_ci(v[-1], lo[-1], hi[-1]))
        rows.append(cells)
    note = H.note(f"Not among the tasks of {', '.join(without)}.") if without else ""
    return H.table(header, rows, numeric=(2, 3)) + note


def _recording_cell(run: RunData, e, out: Path):
    """The episode's episode.rrd (--rerun save) as a link with the command that opens it; else the command that builds
    one from the run's files."""
    view = f"octo-harness view {run.record.path} --task {e.task} --episode {e.episode}"
    if not e.ok:
        return ""
    rrd = e.directory / "episode.rrd"
    if rrd.is_file():
        rel = os.path.relpath(rrd, out)
        return H.Raw(f"<a href='{H.esc(rel)}'>episode.rrd</a><br><code>rerun {H.esc(rrd)}</code><br>"
                     f"or <code>{H.esc(view)}</code>")
    return H.Raw(f"<span class='absent'>none recorded;</span> <code>{H.esc(view)}</code>")


def _episode_rows(run: RunData, task: str, out: Path) -> tuple[str, str]:
    """(table html, videos html) for the episodes of a task."""
    rows, videos = [], []
    rep = representative(run, task)
    for e in run.record.task_episodes(task):
        if not e.ok:
            note = H.Raw(f"<span style='color:#c0392b'>failed: {H.esc(e.error or 'error')}</span>")
        elif (task, e.episode) in run.errors:
            note = H.Raw(f"<span style='color:#c0392b'>not analysed: {H.esc(run.errors[(task, e.episode)])}</span>")
        else:
            note = "representative episode (overlays)" if rep is not None and e.episode == rep.episode else ""
        value = episode_headline(run, e)
        rows.append([e.episode, "" if e.seed is None else e.seed, e.status, "yes" if e.success else "no", e.steps,
                     H.fmt(value) if math.isfinite(value) else H.absent("n/a"), note, _recording_cell(run, e, out)])
        if e.ok and e.video_path is not None:
            rel = os.path.relpath(e.video_path, out)
            videos.append(H.video(rel, f"episode {e.episode} (seed {e.seed}) — {'success' if e.success else 'no success'}"))
    table = H.table(["episode", "seed", "status", "success", "steps", "target lift (last layer, mean over steps)", "note",
                     "recording (Rerun)"],
                    rows, numeric=(0, 1, 4, 5))
    return table, "".join(videos)


def _manifest_section(run: RunData) -> str:
    from harness.run.preflight import summary as preflight_summary

    r = run.record
    parts = []
    if r.model.is_random:
        parts.append(H.banner(f"RANDOM WEIGHTS: {r.model.source} has random weights — its actions and attention are "
                              "not a trained policy's. This run checks the pipeline, not Octo's behaviour.", danger=True))
    protocol = r.manifest.get("protocol") or r.manifest
    execution = protocol.get("execution")
    pairs = [
        ("run", f"{r.name} ({r.path})"),
        ("format", r.format),
        ("status", f"{r.status}; {len(r.episodes)} of {len(r.jobs)} jobs finished, {r.missing} missing"),
        ("model", r.model.source + (" [RANDOM WEIGHTS]" if r.model.is_random else "")),
        ("model note", r.model.note or "—"),
        ("text tokenizer", r.model.text_tokenizer or "—"),
        ("dataset key (action statistics)", r.model.dataset_key or "none"),
        ("execution", execution if isinstance(execution, str) else (str(execution) if execution else "—")),
        ("tasks", ", ".join(r.tasks)),
        ("episodes per task, seed", f"{protocol.get('episodes', '?')}, {protocol.get('seed', '?')}"),
        ("max steps", protocol.get("max_steps") if protocol.get("max_steps") is not None else "task default"),
        ("created", r.created or "—"),
        ("git commit", r.git_commit or "—"),
        ("pre-flight check", preflight_summary(r.manifest.get("preflight"))),
        ("versions", ", ".join(f"{k} {v}" for k, v in sorted(r.versions.items())) or "—"),
    ]
    if "protocol_hash" in r.manifest:
        pairs.append(("protocol hash", r.manifest["protocol_hash"]))
    parts.append(H.key_values(pairs))
    return H.section(f"Manifest: {run.label}", "".join(parts), anchor=H.anchor_id("manifest-" + run.label), level=3)


def _status_banners(runs: list[RunData]) -> str:
    out = []
    for run in runs:
        r = run.record
        if r.model.is_random:
            out.append(H.banner(f"{run.label}: RANDOM WEIGHTS ({r.model.source}) — actions and attention are not a "
                                "trained policy's.", danger=True))
        if r.missing:
            per_task = ", ".join(f"{t}: {n}" for t, n in r.missing_by_task().items() if n)
            state = {"running": "is still running", "interrupted": "was interrupted"}.get(r.status, "is incomplete")
            out.append(H.banner(f"{run.label} {state}: {r.missing} of {len(r.jobs)} episodes missing ({per_task}). "
                                f"This report shows the {len(r.episodes)} finished episodes."))
        failed = [e for e in r.episodes if not e.ok]
        if failed:
            out.append(H.banner(f"{run.label}: {len(failed)} episode(s) failed with an error (listed per task); they "
                                "have no attention and are left out of success rates and attention statistics."))
        if run.errors:
            out.append(H.banner(f"{run.label}: {len(run.errors)} finished episode(s) could not be analysed "
                                "(listed per task)."))
        if not r.attention:
            out.append(H.banner(no_attention_line([run], "in " + run.label)
                                + ": success, episodes and videos are shown, attention figures and tables are not."))
        if run.summaries and run.headline is None:
            out.append(H.banner(f"{run.label} recorded no target masks: target and robot metrics are absent "
                                "(not zero). Run without --no-masks to get them."))
    return "".join(out)


class _Plots:
    """Collects figure PNGs: written to plots/<name>.png and inlined in the page."""

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}

    def add(self, name: str, png: bytes, alt: str, caption: str) -> str:
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
        self.files[safe + ".png"] = png
        return H.image(png, alt, caption + f" (plots/{safe}.png)")


def _cross_task(runs: list[RunData], tasks: list[str], plots: _Plots) -> str:
    body = []
    series = []
    for run in runs:
        data = {t: (s["success_rate"], s["ci_low"], s["ci_high"], s["n"]) for t, s in run.success.items()}
        series.append((run.label, run.colour, data))
    body.append(plots.add("success_by_task", figures.success_chart(tasks, series), "success rate per task",
                          "Success rate per task with 95% Wilson intervals (finished, non-errored episodes; n above "
                          "each bar)."))
    panels = []
    for run in runs:
        layers = max((s.layers for s in run.summaries.values()), default=0)
        matrix = np.full((len(tasks), max(layers, 1)), np.nan)
        for i, t in enumerate(tasks):
            found = run.layer_values(t, run.headline) if run.headline else None
            if found is not None:
                matrix[i, : len(found[0])] = found[0]
        panels.append((run.label, run.colour, matrix))
    if any(np.isfinite(m).any() for _, _, m in panels):
        body.append(plots.add("target_lift_task_layer", figures.task_layer_heatmaps(tasks, panels, "target lift (1 = chance)"),
                              "target lift per task and layer",
                              "Target lift (attention mass on the target mask / mask area; 1 = chance, blue below, red "
                              "above) per task and layer, mean over episodes; one panel per task when the runs hold different "
                              "tasks; grey n/a = absent."))
    elif no_attention_line(runs):
        body.append(H.note(f"Target lift: absent — {no_attention_line(runs)}."))
    else:
        body.append(H.note("Target lift: absent — no run recorded target masks."))
    categories = share_categories(runs)
    share_panels = []
    for run in runs:
        layers = max((s.layers for s in run.summaries.values()), default=1)
        data = {}
        for label, metric in categories:
            matrix = np.full((len(tasks), max(layers, 1)), np.nan)
            for i, t in enumerate(tasks):
                found = run.layer_values(t, metric)
                if found is not None:
                    matrix[i, : len(found[0])] = found[0]
            data[label] = matrix
        share_panels.append((run.label, run.colour, data))
    if categories:
        body.append(plots.add("modality_shares_task_layer",
                              figures.shares_heatmaps(tasks, [c for c, _ in categories], share_panels),
                              "modality shares per task and layer",
                              "Share of the readout's attention per token group (columns; one row of panels per run) by "
                              "task and layer, mean over episodes; 'earlier timesteps' is the share on observation "
                              "history (a separate split)."))
    prog: dict[str, list] = {}
    for t in tasks:
        prog[t] = []
        for run in runs:
            if not run.headline:
                continue
            layers = max((s.layers for s in run.summaries.values()), default=0)
            found = run.progress_values(t, run.headline, layers - 1)
            if found is not None:
                x = (np.arange(len(found[0])) + 0.5) / len(found[0])
                prog[t].append((run.label, run.colour, x, *found))
    if any(prog.values()):  # a panel per task that has data
        shown = [t for t in tasks if prog[t]]
        body.append(plots.add("target_lift_progress", figures.progress_small_multiples(shown, prog, "target lift, last layer"),
                              "target lift along episode progress",
                              "Target lift at the last layer along normalised episode progress (bins of step / steps), "
                              "mean over episodes with 95% bootstrap bands; dotted line = chance"
                              + (f"; no target masks: {', '.join(t for t in tasks if not prog[t])}" if len(shown) < len(tasks)
                                 else "") + "."))
    legend = " ".join(H.swatch(r.colour, r.label) for r in runs)
    return H.section("Cross-task comparison", H.Raw(f"<p>{legend}</p>") + "".join(body), anchor="cross-task")


def _task_section(runs: list[RunData], task: str, out: Path, plots: _Plots, overlays: dict) -> str:
    body = [_task_table(runs, task)]
    safe = H.anchor_id(task)[2:]
    for run in runs:
        if task not in run.record.tasks:
            continue
        future = overlays.get((run.label, task))
        if future is not None:
            overlay = future.result()
            if overlay is not None:
                body.append(plots.add(f"overlays_{safe}_{run.label}", overlay[0], f"overlays {task} {run.label}",
                                      f"{run.label}: layer x time grids of head-mean readout attention, every camera the model "
                                      f"reads side by side ({overlay[1]}); "
                                      "the representative episode is the one whose target lift (last layer) is closest "
                                      "to the task's median (the first analysed episode without masks)."))
    head_panels = []
    for run in runs:
        matrix = run.head_values(task, run.headline) if run.headline else None
        if matrix is not None:
            head_panels.append((run.label, run.colour, matrix))
    if head_panels:
        body.append(plots.add(f"head_layer_lift_{safe}", figures.head_layer_maps(head_panels, "target lift (1 = chance)"),
                              f"target lift per head {task}",
                              "Target lift per layer and head (which heads follow the object), mean over episodes."))
    elif no_attention_line([r for r in runs if task in r.record.tasks]):
        body.append(H.note(f"Attention: {no_attention_line([r for r in runs if task in r.record.tasks])}."))
    else:
        body.append(H.note("Target lift per head: absent (no target mask coverage recorded for this task)."))
    lines = []
    for run in runs:
        if not run.headline:
            continue
        layers = max((s.layers for s in run.summaries.values()), default=0)
        for outcome in ("success", "no_success"):
            found = run.progress_values(task, run.headline, layers - 1, outcome)
            if found is not None:
                x = (np.arange(len(found[0])) + 0.5) / len(found[0])
                lines.append((run.label, run.colour, outcome, x, *found))
    if lines:
        body.append(plots.add(f"target_lift_progress_{safe}", figures.progress_by_outcome(lines, "target lift, last layer"),
                              f"target lift along progress {task}",
                              "Target lift at the last layer along episode progress, successful (solid) vs "
                              "unsuccessful (dashed) episodes, 95% bootstrap bands."))
    share_panels = []
    for run in runs:
        data = {}
        for label, metric in share_categories([run]):
            if metric.startswith("share/"):
                found = run.layer_values(task, metric)
                if found is not None:
                    data[label] = found[0]
        if data:
            share_panels.append((run.label, run.colour, data))
    if share_panels:
        body.append(plots.add(f"modality_shares_{safe}", figures.shares_by_layer(share_panels, SHARE_COLOURS),
                              f"modality shares {task}", "Modality shares of the readout attention along layers."))
    for run in runs:
        if task not in run.record.tasks:
            continue
        table, videos = _episode_rows(run, task, out)
        body.append(H.section(f"Episodes: {run.label}", table + (H.details(f"videos ({run.label})", H.Raw(
            f"<div class='videos'>{videos}</div>"), open_=False) if videos else H.note("no rollout.mp4 in this run")),
            level=3))
    return H.section(f"Task: {task}", "".join(body), anchor=H.anchor_id("task-" + task))


_DEFINITIONS = """
<ul>
<li><b>Readout attention</b>: the post-softmax attention rows of the last timestep's readout token(s) over every key,
per layer and head (what the action head reads from). Head-mean values use the mean row over heads and readouts,
as in <code>metrics.jsonl</code>.</li>
<li><b>Modality share</b>: fraction of a row's mass on a token group (primary camera, wrist camera, language, readouts,
other groups such as proprio); the groups partition the keys, so shares sum to 1. <b>Earlier timesteps</b>: the
fraction on the observation history (all groups of earlier window steps), a separate split.</li>
<li><b>Target mass</b>: the fraction of the camera's current-timestep attention inside the target's segmentation mask
(each patch weighted by the share of its pixels in the mask). <b>Target lift</b> = target mass / mask area: 1 is
chance (uniform attention), 1/area means all attention on the target. Steps where the target is not visible have no
value. <b>Robot mass</b>: the same for the robot's mask.</li>
<li><b>Entropy</b>: entropy (nats) of each attention row, mean over heads and readouts.</li>
<li><b>Episode progress</b>: step t of an n-step episode falls in bin floor(t &middot; bins / n); values are averaged per
episode and bin, then over episodes.</li>
<li><b>Intervals</b>: success: Wilson score interval over non-errored episodes. Attention: 95% percentile bootstrap over
episodes (2000 resamples by default, fixed seed); one episode gives no interval. Outcome splits: successful vs
unsuccessful episodes.</li>
</ul>
"""

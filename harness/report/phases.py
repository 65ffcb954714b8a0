"""The report's Phases section: does attention move as the task unfolds, and where do failures stop?

For every finished episode of a task with phases (attention.npz `phase`, envs.phases), the lift of the target,
gripper and goal masks and of the background per step and layer (harness.analysis.phases.phase_lifts) is
averaged per phase and episode; then per run x task:

  phase_table.csv    run, task, phase, camera, mask, layer, value, ci_low, ci_high, n: mean over episodes of the
                     per-episode phase means (percentile bootstrap 95% over episodes)
  phase_steps.csv    run, task, phase, episodes_reached, steps_mean, furthest, furthest_failed: how many episodes
                     reached each phase, the mean steps spent in it, and how many (failed) episodes stopped there
  phase_tests.csv    run, task, camera, mask, layer, test, statistic, p, episodes, phases, means: the paired test
                     across phases (Friedman on per-episode phase means; Wilcoxon with two phases)
  phase_events.csv   run, task, event, camera, mask, layer, offset, value, ci_low, ci_high, n: lift aligned on the
                     onset of each phase (grasp onset, lift-off, place onset, release), WINDOW steps either side
  phase_failures.csv run, task, phase, camera, mask, layer, failed_mean, success_mean, p, n_failed, n_success: in the
                     phase where failed episodes stopped, their attention against successful episodes' in that phase

`tables(runs)` -> those CSVs; `section(runs, plots)` -> HTML ("" when no run recorded phases); `markdown(runs)` ->
the tables and sentences as Markdown (python -m harness.report.phases RUN...).
"""

from __future__ import annotations

import io
import math
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from harness.analysis import phases as P
from harness.analysis.runs import read_npz
from harness.report import html as H
from harness.report.figures_file import markdown_table
from harness.report.rundata import csv_bytes as _csv

WINDOW = 10  # steps either side of an event
TABLE_COLUMNS = ("run", "task", "phase", "camera", "mask", "layer", "value", "ci_low", "ci_high", "n")
STEPS_COLUMNS = ("run", "task", "phase", "episodes", "episodes_reached", "steps_mean", "furthest", "furthest_failed")
TEST_COLUMNS = ("run", "task", "camera", "mask", "layer", "test", "statistic", "p", "episodes", "phases", "means")
EVENT_COLUMNS = ("run", "task", "event", "camera", "mask", "layer", "offset", "value", "ci_low", "ci_high", "n")
FAILURE_COLUMNS = ("run", "task", "phase", "camera", "mask", "layer", "failed_mean", "success_mean", "p", "n_failed",
                   "n_success")
MEASURES = (*P.MASKS, "background")


@dataclass(frozen=True, eq=False)
class EpisodePhases:
    task: str
    episode: int
    success: bool
    names: tuple[str, ...]
    phase: np.ndarray  # (steps,) int index into names (-1: none)
    furthest: int  # index of the furthest phase reached (the state after the last step included), -1 unknown
    lifts: dict[str, np.ndarray]  # "<cam>/<measure>" -> (steps, layers)


def read_episodes(run) -> list[EpisodePhases]:
    """The finished episodes of a run (RunData or RunRecord) that recorded phases; others are left out."""
    record = getattr(run, "record", run)
    out = []
    for e in record.episodes:
        if not e.ok or not e.attention_path.is_file():
            continue
        try:
            arrays = read_npz(e.attention_path)
        except ValueError:  # a damaged file: the main report names it
            continue
        if "phase" not in arrays or "phase_names" not in arrays:
            continue
        names = tuple(str(n) for n in arrays["phase_names"])
        phase = np.asarray(arrays["phase"], np.int64)
        if phase.ndim != 1 or not names or phase.max(initial=-1) >= len(names):
            continue  # not what the writers store: untrusted input, left out
        furthest = (e.read_json().get("phases") or {}).get("furthest")
        index = names.index(furthest) if furthest in names else int(phase.max(initial=-1))
        lifts = {k: v for k, v in P.phase_lifts(arrays).items() if v.shape[0] == len(phase)}
        out.append(EpisodePhases(e.task, e.episode, bool(e.success), names, phase, index, lifts))
    return out


def _label(run) -> str:
    return getattr(run, "label", getattr(run, "name", ""))


def _by_task(episodes: list[EpisodePhases]) -> dict[str, list[EpisodePhases]]:
    groups: dict[str, list[EpisodePhases]] = defaultdict(list)
    for e in episodes:
        groups[e.task].append(e)
    return dict(groups)


def _keys(episodes: list[EpisodePhases]) -> list[str]:
    return sorted({k for e in episodes for k in e.lifts}, key=lambda k: (k.split("/")[0], MEASURES.index(k.split("/")[1])))


def _phase_means(episodes, key, names) -> np.ndarray:
    """(episodes, phases, layers) per-episode phase means of measure `key` (nan where absent)."""
    layers = max(e.lifts[key].shape[1] for e in episodes if key in e.lifts)
    out = np.full((len(episodes), len(names), layers), np.nan)
    for i, e in enumerate(episodes):
        if key in e.lifts:
            out[i] = P.phase_means(e.phase, e.lifts[key], len(names))
    return out


def summarise(run, resamples: int = 2000, seed: int = 0) -> dict[str, list[tuple]]:
    """{table name: rows} for one run."""
    label = _label(run)
    rows: dict[str, list[tuple]] = {name: [] for name in ("table", "steps", "tests", "events", "failures")}
    for task, episodes in _by_task(read_episodes(run)).items():
        names = episodes[0].names
        episodes = [e for e in episodes if e.names == names]
        for k, phase in enumerate(names):
            reached = [e for e in episodes if e.furthest >= k]
            spent = [int((e.phase == k).sum()) for e in episodes]
            rows["steps"].append((label, task, phase, len(episodes), len(reached), float(np.mean(spent)),
                                  sum(e.furthest == k for e in episodes),
                                  sum(e.furthest == k and not e.success for e in episodes)))
        for key in _keys(episodes):
            camera, measure = key.split("/")
            means = _phase_means(episodes, key, names)  # (episodes, phases, layers)
            mean, lo, hi, n = P.bootstrap_mean_ci(means, resamples=resamples, seed=seed)
            for k, phase in enumerate(names):
                for layer in range(means.shape[2]):
                    rows["table"].append((label, task, phase, camera, measure, layer, float(mean[k, layer]),
                                          float(lo[k, layer]), float(hi[k, layer]), int(n[k, layer])))
            for layer in range(means.shape[2]):
                t = P.phase_test(means[:, :, layer])
                rows["tests"].append((label, task, camera, measure, layer, t.test, t.statistic, t.p, t.episodes,
                                      " ".join(names[k] for k in t.phases), " ".join(f"{m:.4g}" for m in t.means)))
            events: dict[str, list[np.ndarray]] = defaultdict(list)
            for e in episodes:
                if key in e.lifts:
                    for event, onset in P.onsets(e.phase, names).items():
                        events[event].append(P.align(e.lifts[key], onset, WINDOW))
            for event, aligned in events.items():
                mean, lo, hi, n = P.aligned_band(aligned, resamples=resamples, seed=seed)
                for i, offset in enumerate(range(-WINDOW, WINDOW + 1)):
                    for layer in range(mean.shape[1]):
                        rows["events"].append((label, task, event, camera, measure, layer, offset, float(mean[i, layer]),
                                               float(lo[i, layer]), float(hi[i, layer]), int(n[i, layer])))
            failed = [i for i, e in enumerate(episodes) if not e.success]
            ok = [i for i, e in enumerate(episodes) if e.success]
            for k in sorted({episodes[i].furthest for i in failed if episodes[i].furthest >= 0}):
                stopped = [i for i in failed if episodes[i].furthest == k]
                for layer in range(means.shape[2]):
                    fm, sm, p, nf, ns = P.failure_contrast(means[stopped, k, layer], means[ok, k, layer])
                    rows["failures"].append((label, task, names[k], camera, measure, layer, fm, sm, p, nf, ns))
    return rows




def _all(runs) -> list[dict[str, list[tuple]]]:
    return [summarise(run) for run in runs]


def tables(runs, summaries: list | None = None) -> dict[str, bytes]:
    """{"phase_table.csv", "phase_steps.csv", "phase_tests.csv", "phase_events.csv", "phase_failures.csv"}."""
    summaries = summaries if summaries is not None else _all(runs)
    join = lambda name: [r for s in summaries for r in s[name]]  # noqa: E731
    return {"phase_table.csv": _csv(TABLE_COLUMNS, join("table")), "phase_steps.csv": _csv(STEPS_COLUMNS, join("steps")),
            "phase_tests.csv": _csv(TEST_COLUMNS, join("tests")), "phase_events.csv": _csv(EVENT_COLUMNS, join("events")),
            "phase_failures.csv": _csv(FAILURE_COLUMNS, join("failures"))}


def _headline(rows: list[tuple], task: str) -> tuple[str, int] | None:
    """(camera, last layer) the sentences speak of: image_primary when measured, else the first camera."""
    items = [r for r in rows if r[1] == task]
    if not items:
        return None
    cameras = sorted({r[2] for r in items})
    camera = "image_primary" if "image_primary" in cameras else cameras[0]
    return camera, max(r[4] for r in items if r[2] == camera)


PHASE_TEST_HEADER = ("measure", "lift per phase", "test", "p", "episodes", "changes across phases")
FAILURE_HEADER = ("phase", "target lift: failed", "successful", "Mann-Whitney p")
_TEST_NAMES = {"friedman": "Friedman", "wilcoxon": "Wilcoxon"}


def _headline_tests(task: str, summary: dict[str, list[tuple]]) -> tuple[tuple | None, list[tuple]]:
    head = _headline(summary["tests"], task)
    if head is None:
        return None, []
    camera, layer = head
    return head, [r for r in summary["tests"] if r[1] == task and r[2] == camera and r[4] == layer and r[5] != "none"]


def phase_test_rows(task: str, summary: dict[str, list[tuple]], alpha: float = 0.05) -> list[tuple[str, ...]]:
    """The phase test per measure on the headline camera's last layer as table cells (PHASE_TEST_HEADER)."""
    _, tests = _headline_tests(task, summary)
    return [(r[3], ", ".join(f"{p} {float(m):.2f}" for p, m in zip(r[9].split(), r[10].split())), _TEST_NAMES[r[5]],
             f"{r[7]:.2g}", str(r[8]), "yes" if r[7] < alpha else "not detectably") for r in tests]


def sentence(task: str, summary: dict[str, list[tuple]], alpha: float = 0.05) -> str:
    """A verdict line (at most about 25 words): which measures change across phases on the headline camera's last
    layer. The figures behind it (lift per phase, test, p, episodes) are phase_test_rows'."""
    head, tests = _headline_tests(task, summary)
    if head is None:
        if any(r[1] == task for r in summary["steps"]):
            return f"{task}: phases recorded but no mask measures (a run with --no-masks): nothing to test."
        return f"{task}: no phases recorded."
    if not tests:
        return f"{task}: too few episodes visited two phases to test whether attention changes across them."
    camera, layer = head
    changed = [r[3] for r in tests if r[7] < alpha]
    return f"{task}, {camera}, layer {layer}: " + (f"attention changes across phases for {', '.join(changed)}."
                                                   if changed else "no measured attention changes detectably across phases.")


def failure_rows(task: str, summary: dict[str, list[tuple]]) -> list[tuple[str, ...]]:
    """Target lift where failed episodes stopped against successful episodes' there, headline camera and layer, as
    table cells (FAILURE_HEADER)."""
    head = _headline(summary["tests"], task)
    if head is None:
        return []
    camera, layer = head
    return [(r[2], f"{r[6]:.2f}", f"{r[7]:.2f}", f"{r[8]:.2g}" if math.isfinite(r[8]) else "-")
            for r in summary["failures"] if r[1] == task and r[3] == camera and r[4] == "target" and r[5] == layer
            and math.isfinite(r[6]) and math.isfinite(r[7])]


def failure_sentence(task: str, summary: dict[str, list[tuple]]) -> str:
    """Where failed episodes stopped, in one short line; their target lift there is failure_rows'."""
    steps = [r for r in summary["steps"] if r[1] == task]
    failed = {r[2]: r[7] for r in steps if r[7]}
    if not steps:
        return f"{task}: no phases recorded."
    if not failed:
        return f"{task}: no failed episode among {steps[0][3]}."
    return f"{task}: failed episodes stopped in " + ", ".join(f"{phase} ({n})" for phase, n in failed.items()) + "."


def event_figure(task: str, summary: dict[str, list[tuple]]) -> bytes | None:
    """PNG: one panel per event, lift of each measure (headline camera, last layer) against steps from the event,
    with its 95% bootstrap band."""
    head = _headline(summary["tests"], task)
    rows = [r for r in summary["events"] if r[1] == task]
    if head is None or not rows:
        return None
    camera, layer = head
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    events = list(dict.fromkeys(r[2] for r in rows))
    colours = {"target": "#c44e52", "gripper": "#4c72b0", "goal": "#55a868", "background": "#999999"}
    fig, axes = plt.subplots(1, len(events), figsize=(3.0 * len(events) + 0.6, 2.6), dpi=110, squeeze=False,
                             sharey=True)
    for ax, event in zip(axes[0], events):
        for measure, colour in colours.items():
            sel = sorted((r for r in rows if r[2] == event and r[3] == camera and r[4] == measure and r[5] == layer),
                         key=lambda r: r[6])
            if not sel:
                continue
            x = [r[6] for r in sel]
            ax.plot(x, [r[7] for r in sel], color=colour, label=measure, lw=1.5)
            ax.fill_between(x, [r[8] for r in sel], [r[9] for r in sel], color=colour, alpha=0.18, lw=0)
        ax.axvline(0, color="#333333", lw=0.8, ls="--")
        ax.axhline(1, color="#999999", lw=0.6, ls=":")
        n = max((r[10] for r in rows if r[2] == event and r[6] == 0), default=0)
        ax.set_title(f"{event} ({n} episodes)", fontsize=9)
        ax.set_xlabel("steps from the event", fontsize=8)
    axes[0][0].set_ylabel(f"lift, {camera.removeprefix('image_')}, layer {layer}", fontsize=8)
    axes[0][-1].legend(fontsize=7, loc="upper right")
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def _phase_rows(summary, task: str) -> tuple[list[str], list[list]]:
    """Header and rows of the phase x layer table (headline camera): one row per measure and layer."""
    head = _headline(summary["tests"], task)
    names = [r[2] for r in summary["steps"] if r[1] == task]
    if head is None:
        return [], []
    camera, _ = head
    cells = {(r[4], r[5], r[2]): r for r in summary["table"] if r[1] == task and r[3] == camera}
    layers = sorted({r[5] for r in summary["table"] if r[1] == task and r[3] == camera})
    out = []
    for measure in MEASURES:
        for layer in layers:
            if (measure, layer, names[0]) not in cells:
                continue
            row = [measure, layer]
            for phase in names:
                r = cells[(measure, layer, phase)]
                row.append((r[6], r[7], r[8], r[9]))
            out.append(row)
    return ["measure", "layer", *names], out


def section(runs, plots, summaries: list | None = None) -> str:
    """The page's Phases section ("" when no run recorded phases)."""
    summaries = summaries if summaries is not None else _all(runs)
    body = []
    for run, summary in zip(runs, summaries):
        tasks = list(dict.fromkeys(r[1] for r in summary["steps"]))
        for task in tasks:
            body.append(H.section(f"{task}: {_label(run)}", "", level=3))
            steps = [r for r in summary["steps"] if r[1] == task]
            body.append(H.table(("phase", "episodes reaching it", "mean steps in it", "stopped here", "failed, stopped here"),
                                [(r[2], f"{r[4]}/{r[3]}", f"{r[5]:.1f}", r[6], r[7]) for r in steps], numeric=(2, 3, 4)))
            body.append(H.Raw(f"<p>{H.esc(sentence(task, summary))}</p>"))
            if (tested := phase_test_rows(task, summary)):
                body.append(H.table(PHASE_TEST_HEADER, tested, numeric=(4,)))
            body.append(H.Raw(f"<p>{H.esc(failure_sentence(task, summary))}</p>"))
            if (stopped := failure_rows(task, summary)):
                body.append(H.table(FAILURE_HEADER, stopped))
            png = event_figure(task, summary)
            if png is not None:
                body.append(plots.add(f"phase_events_{H.anchor_id(task)[2:]}_{_label(run)}", png, f"event-aligned lift {task}",
                                      f"Lift (1 = chance) of the target, gripper, goal and background aligned on each "
                                      f"phase's onset, ±{WINDOW} steps, mean over episodes with a 95% bootstrap band "
                                      "(tables/phase_events.csv)."))
            header, rows = _phase_rows(summary, task)
            if rows:
                camera = _headline(summary["tests"], task)[0]
                body.append(H.details(f"phase x layer table ({camera}, lift, mean [95%] over episodes)",
                                      str(H.table(header, [(m, layer, *[H.fmt_ci(v, lo, hi, 2) if math.isfinite(v) else
                                                                         H.absent("n/a") for v, lo, hi, n in cells])
                                                           for m, layer, *cells in rows], numeric=(1,))), open_=True))
    if not body:
        return ""
    intro = H.note("Task phases are read off the simulator state (envs.phases: approach, grasp, lift or transport, "
                   "place, release), never off the policy. Lift = attention mass on a mask / the mask's area "
                   "(1 = chance); background = pixels in no mask. The test compares each episode's phase means "
                   "across phases (Friedman; Wilcoxon with two phases), over the episodes that visited every "
                   "compared phase. Tables: tables/phase_*.csv.")
    return H.section("Phases", intro + "".join(str(b) for b in body), anchor="phases")


def markdown(runs) -> str:
    """Per run and task: the phase steps table, the target/gripper/goal/background phase table on the headline
    camera's last layer, the test sentence and where failures stop (EVAL.md, docs)."""
    lines = []
    for run in runs:
        summary = summarise(run)
        for task in dict.fromkeys(r[1] for r in summary["steps"]):
            steps = [r for r in summary["steps"] if r[1] == task]
            lines += [f"#### {task} ({_label(run)})", "", "| phase | episodes reaching it | mean steps in it | "
                      "stopped here (failed) |", "|---|---:|---:|---:|"]
            lines += [f"| {r[2]} | {r[4]}/{r[3]} | {r[5]:.1f} | {r[6]} ({r[7]}) |" for r in steps]
            header, rows = _phase_rows(summary, task)
            head = _headline(summary["tests"], task)
            if rows and head:
                lines += ["", f"Lift on {head[0]} per phase (mean [95% bootstrap] over episodes):", "",
                          "| " + " | ".join(header) + " |", "|---|---:|" + "---|" * (len(header) - 2)]
                for m, layer, *cells in rows:
                    lines.append(f"| {m} | {layer} | " + " | ".join(
                        f"{v:.2f} [{lo:.2f}, {hi:.2f}]" if math.isfinite(v) and math.isfinite(lo) else
                        (f"{v:.2f}" if math.isfinite(v) else "n/a") for v, lo, hi, n in cells) + " |")
            lines += ["", sentence(task, summary), ""]
            if (tested := phase_test_rows(task, summary)):
                lines += [*markdown_table(PHASE_TEST_HEADER, tested), ""]
            lines += [failure_sentence(task, summary), ""]
            if (stopped := failure_rows(task, summary)):
                lines += [*markdown_table(FAILURE_HEADER, stopped), ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    """`python -m harness.report.phases RUN... [--eval-md EVAL.md]`: the "Phases and position" section (the phase
    tables, then harness.report.position's), printed; with --eval-md also written there (harness.report.eval_md)."""
    from harness.report import position
    from harness.report.eval_md import section_main, tables_section

    def body(records) -> str:
        steps, where = markdown(records), position.markdown(records)
        if not steps.strip():
            return ""
        return "\n\n".join(["### Phases", steps.strip("\n")] + (["### Position", where.strip("\n")] if where.strip() else []))

    return section_main(argv, "python -m harness.report.phases", "Write the Phases and position section of an EVAL.md.",
                        tables_section("## Phases and position", body,
                                       "no run here has phase rows: give runs made with masks on (the default)"))


if __name__ == "__main__":
    raise SystemExit(main())

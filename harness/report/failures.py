"""The report's Failures section (issue 74, "why an episode failed"): per task, one line per failed episode and a
picture of where it stalled beside a successful episode at the same phase.

- `summarise(runs)`: diagnose's rows, not computed again here: `episode_signals` for every finished episode of the
  tasks that have a failure, then `failure_rows` (harness.analysis.diagnose), each run named by its report label;
  None when no episode failed (the section is then absent).
- `tables(summary)`: {"failures.csv"}: every row, in diagnose's FAILURE_COLUMNS, the bytes diagnose writes.
- `section(runs, figures, summary)`: per task the table (its first SHOWN_FAILURES rows, as diagnose.md) and one
  figure: up to PICTURED failed episodes (the largest |z| of a signal first, then in run and seed order), each shown
  stalled beside a successful episode leaving the same phase (`shown_step`: the failure at the step the successes
  had passed its furthest phase, their median, not before its stall step; the success at its last step in that
  phase; without phases, both at the first step of their last tenth), the success from the same run and condition,
  else the same condition, else any run of the task (the figure says which). A failure that never left its first
  phase stalls at step 0, where every episode looks alike: the step the successes moved on is the telling one. Its
  frames come from `harness.report.failure_frames`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from harness.analysis.diagnose.failures import Z_SIGNALS, Z_SIGNALS_TEXT, failure_rows
from harness.analysis.diagnose.signals import EpisodeSignals, condition_name, episode_signals, preflight_text
from harness.analysis.diagnose.stats import stall_step
from harness.analysis.diagnose.outputs import SHOWN_FAILURES, failures_csv
from harness.report import failure_frames as F
from harness.report import html as H

PICTURED = 4  # failed episodes a task in its figure
TIERS = ("same run and condition", "same condition, another run", "another condition")
HEADER = ("run", "condition", "seed", "episode", "steps", "furthest phase", "stall step",
          "successes passed it (median step)", "furthest signals (robust z)", "pre-flight", "in the figure")
NO_FRAMES = ("no frames were recorded for its failed episodes (runs with --no-video and without --record-inputs): "
             "run without --no-video, or with --record-inputs, to see each stall beside a success")


@dataclass
class Summary:
    rows: list[dict]  # failure_rows: one per failed episode, run label, task, seed order
    episodes: list[EpisodeSignals]  # every finished episode of the tasks with a failure, in run and job order
    where: dict[tuple[str, str, int], tuple]  # (run label, task, episode) -> (RunData, EpisodeRecord)
    notes: list[str] = field(default_factory=list)  # episodes left out and why

    def signals(self, run: str, task: str, episode: int) -> EpisodeSignals:
        return next(e for e in self.episodes if (e.run, e.task, e.episode) == (run, task, episode))


@dataclass(frozen=True)
class Match:
    """The successful episode shown beside a failure."""

    episode: EpisodeSignals
    step: int  # its last step in the failure's furthest phase (without phases: the first of its last tenth)
    tier: int  # index into TIERS


def _finished(e) -> bool:
    return e.ok and e.steps > 0


def summarise(runs) -> Summary | None:
    """diagnose's failure rows over the runs (RunData), or None when no finished episode failed."""
    failing = {e.task for run in runs for e in run.record.episodes if _finished(e) and not e.success}
    if not failing:
        return None
    episodes, where, notes = [], {}, []
    for run in runs:
        record = run.record
        condition, preflight = condition_name(record.manifest), preflight_text(record.manifest)
        for e in record.episodes:
            if not _finished(e) or e.task not in failing:  # another task's successes are no failure's peers
                continue
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    found = episode_signals(record, e, condition, preflight, features=False)
            except (OSError, ValueError) as exc:  # a damaged file: that episode is left out, named
                notes.append(f"{run.label}/{e.task}/episode_{e.episode}: left out ({str(exc).splitlines()[0][:200]})")
                continue
            found.run = run.label  # the report's name for the run
            episodes.append(found)
            where[(run.label, e.task, e.episode)] = (run, e)
    rows = failure_rows(episodes)
    return Summary(rows, episodes, where, notes) if rows else None


def tables(summary: Summary | None) -> dict[str, bytes]:
    return {"failures.csv": failures_csv(summary.rows).encode()} if summary is not None else {}


def _largest_z(row: dict) -> float:
    values = [abs(float(row[f"z_{s}"])) for s in Z_SIGNALS if row[f"z_{s}"] != ""]
    return max(values) if values else -1.0


def pictured(rows: list[dict], summary: Summary) -> list[dict]:
    """Up to PICTURED of a task's failure rows whose episode recorded frames: the largest |z| first, then in row
    (run, seed) order."""
    framed = [(i, r) for i, r in enumerate(rows) if F.source(summary.where[(r["run"], r["task"], r["episode"])][1])]
    return [r for _, r in sorted(framed, key=lambda ir: (-_largest_z(ir[1]), ir[0]))[:PICTURED]]


def success_for(failed: EpisodeSignals, summary: Summary) -> Match | None:
    """The successful episode of the failure's task to show beside it: one that reached the failure's furthest phase
    and recorded frames, from the same run and condition, else the same condition, else any (first in run and job
    order within each); None when there is none."""
    furthest = int(failed.phase.max()) if failed.has_phases else None
    best = None
    for index, e in enumerate(summary.episodes):
        if not e.success or e.task != failed.task or not F.source(summary.where[(e.run, e.task, e.episode)][1]):
            continue
        if furthest is not None and not (e.has_phases and (e.phase == furthest).any()):
            continue
        tier = 0 if (e.run, e.condition) == (failed.run, failed.condition) else 1 if e.condition == failed.condition else 2
        if best is None or (tier, index) < best[:2]:
            best = (tier, index, e)
    if best is None:
        return None
    tier, _, e = best
    step = int(np.flatnonzero(e.phase == furthest)[-1]) if furthest is not None else stall_step(None, e.steps)
    return Match(e, step, tier)


def shown_step(row: dict, failed: EpisodeSignals) -> int:
    """The failure's step in the figure: with phases, the step at which the successes had passed its furthest phase
    (their median), not before its stall step and not past its end; without phases (or no success to time it),
    its stall step."""
    stall = int(row["stall_step"])
    if not row["furthest_phase"] or not row["passed_median"]:
        return stall
    return int(min(max(stall, round(float(row["passed_median"]))), failed.steps - 1))


def _no_success(failed: EpisodeSignals, row: dict, summary: Summary) -> str:
    """Why a failure has no success beside it (success_for found none)."""
    successes = [e for e in summary.episodes if e.success and e.task == failed.task]
    if not successes:
        return f"no episode of {failed.task} succeeded"
    if row["furthest_phase"] and not any(e.has_phases and (e.phase == failed.phase.max()).any() for e in successes):
        return f"no successful episode of {failed.task} reached {row['furthest_phase']}"
    return f"no successful episode of {failed.task} recorded frames"


def _phase_text(row: dict) -> str:
    return f"last step in {row['furthest_phase']}" if row["furthest_phase"] else "first step of its last tenth"


def _failed_text(row: dict, step: int) -> str:
    if step < int(row["stall_step"]):  # its frames end before the stall (inputs recorded for the first steps only)
        return f"step {step}: its last frame recorded (stall at step {row['stall_step']})"
    if not row["furthest_phase"]:
        return f"step {step}: first step of its last tenth (stall)"
    return f"step {step}: in {row['furthest_phase']} since step {row['stall_step']} (stall)"


def _figure(task: str, rows: list[dict], summary: Summary, figures) -> tuple[str, dict]:
    """(the task's figure HTML or its one line, {(run, episode): figure row number})."""
    chosen = pictured(rows, summary)
    if not chosen:
        return str(H.note(f"{task}: {NO_FRAMES}.")), {}
    pairs = []
    for row in chosen:
        failed = summary.signals(row["run"], task, row["episode"])
        pairs.append((row, failed, success_for(failed, summary)))
    wanted: dict[tuple, set[int]] = {}
    def frame_step(run: str, episode: int, step: int) -> int:  # the step itself, or the last recorded before it
        return F.at_or_before(F.recorded_steps(summary.where[(run, task, episode)][1]), step)

    shown = {id(row): frame_step(row["run"], row["episode"], shown_step(row, failed)) for row, failed, _ in pairs}
    beside = {id(row): frame_step(m.episode.run, m.episode.episode, m.step) for row, _, m in pairs if m is not None}
    for row, _, match in pairs:
        wanted.setdefault((row["run"], task, row["episode"]), set()).add(shown[id(row)])
        if match is not None:
            wanted.setdefault((match.episode.run, task, match.episode.episode), set()).add(beside[id(row)])
    panels = {key: F.panels(*summary.where[key], sorted(steps)) for key, steps in wanted.items()}
    figure_rows, notes = [], []
    for number, (row, failed, match) in enumerate(pairs, 1):
        left = panels[(row["run"], task, row["episode"])].get(shown[id(row)])
        left_lines = (f"FAILED {row['run']} | seed {row['seed']} ep. {row['episode']}"
                      + (f" ({left[1]})" if left else ""), _failed_text(row, shown[id(row)]))
        if match is None:
            why = _no_success(failed, row, summary)
            figure_rows.append((left, left_lines, None, ("no success to show", why)))
            notes.append(f"row {number}: {why}")
            continue
        e = match.episode
        right = panels[(e.run, task, e.episode)].get(beside[id(row)])
        other = "" if match.tier == 0 else f" [{TIERS[match.tier]}" + (f": {e.condition}]" if match.tier == 2 else "]")
        right_lines = (f"SUCCESS {e.run} | seed {e.seed} ep. {e.episode}" + (f" ({right[1]})" if right else "") + other,
                       f"step {beside[id(row)]}: {_phase_text(row)}" if beside[id(row)] == match.step else
                       f"step {beside[id(row)]}: last frame recorded before its {_phase_text(row)} ({match.step})")
        figure_rows.append((left, left_lines, right, right_lines))
        if match.tier:
            notes.append(f"row {number}: the success is from {e.run} ({TIERS[match.tier]}"
                         + (f": {e.condition})" if match.tier == 2 else ")"))
    png = F.compose(f"{task}: failed episodes stalled in a phase (left) beside a success leaving it (right)",
                    figure_rows)
    without = sorted({r.label for r, _ in summary.where.values() if not r.record.attention})
    caption = (f"{task}: up to {PICTURED} failed episodes (the largest |z| of a signal first, then in run and seed "
               "order), each stalled in its furthest phase (left: at the step the successes had passed that phase, "
               "their median, or at its stall step when later) beside a successful episode of the same task at its "
               "last step in that phase (right; without phases, both at the first step of their last tenth), from the "
               "same run and condition where one exists. Each panel: camera | attention overlay, from rollout.mp4 as the run "
               "recorded it (its video overlay, by default the last layer's head mean), else from inputs.npz with the "
               "last layer's head-mean readout attention drawn over the policy's input frame"
               + (f"; {', '.join(without)}: a policy without attention, frames without an overlay" if without else "")
               + "." + ("".join(f" {n[0].upper()}{n[1:]}." for n in notes)))
    html_ = figures.add(f"failures_{H.anchor_id(task)[2:]}", png, f"failed episodes of {task} beside a success", caption)
    return str(html_), {(row["run"], row["episode"]): number for number, (row, _, _) in enumerate(pairs, 1)}


def _cells(row: dict, in_figure: dict) -> tuple:
    number = in_figure.get((row["run"], row["episode"]))
    return (row["run"], row["condition"], row["seed"], row["episode"], row["steps"],
            row["furthest_phase"] or row["stall_basis"], row["stall_step"], row["passed_median"] or H.absent("—"),
            row["furthest"], row["preflight"], f"row {number}" if number else "")


def _task(task: str, rows: list[dict], summary: Summary, figures) -> str:
    finished = sum(e.task == task for e in summary.episodes)
    picture, in_figure = _figure(task, rows, summary, figures)
    body = [f"<p>{len(rows)} of {finished} finished episodes of {H.esc(task)} failed.</p>",
            str(H.table(HEADER, [_cells(r, in_figure) for r in rows[:SHOWN_FAILURES]], numeric=(2, 3, 4, 6, 7)))]
    if len(rows) > SHOWN_FAILURES:
        body.append(str(H.note(f"{len(rows) - SHOWN_FAILURES} more failed episodes of {task} in tables/failures.csv.")))
    return H.section(task, "".join(body) + picture, anchor=H.anchor_id("failures-" + task), level=3)


def section(runs, figures, summary: Summary | None) -> str:
    """The Failures section's HTML ("" when no episode failed); its figures go through `figures.add`."""
    if summary is None:
        return ""
    intro = ("Why each failed episode failed: the rows of octo-harness diagnose's failures.csv (tables/failures.csv). "
             "Stall step: the first step of the furthest phase the episode reached (tasks without phases: the first step "
             "of its last tenth); after it the episode made no more progress. Successes passed it: the median step at "
             "which the successful episodes of the same task and condition passed that phase. Furthest signals: each "
             "signal's mean over the episode's steps in that phase as a robust z-score against those successes' (none "
             f"with fewer than 3 of them): {Z_SIGNALS_TEXT}. docs/diagnose.md explains them.")
    body = [str(H.note(intro))] + [str(H.note(n)) for n in summary.notes]
    tasks = dict.fromkeys(t for run in runs for t in run.record.tasks)
    for task in [t for t in tasks if any(r["task"] == t for r in summary.rows)]:
        body.append(_task(task, [r for r in summary.rows if r["task"] == task], summary, figures))
    return H.section("Failures", "".join(body), anchor="failures")

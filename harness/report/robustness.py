"""The report's Robustness section: success against perturbation level per condition and task (Wilson bands), target
lift and nuisance mass against level, the step-0 attention shift, and the association of nuisance mass with success.

`analyse(records)` reads every perturbed episode once (None when no run was perturbed); the report passes its result to
`tables(records, analysis)` -> {"robustness.csv", "robustness_episodes.csv", "robustness_shift.csv", "robustness_association.csv",
"robustness_paired.csv"} (the paired test of each perturbed cell against the nominal seeds: which cells break a task),
and with --reliance-every runs "robustness_predictors.csv" (harness.analysis.predictors: which of nuisance reliance
and nuisance attention goes with failure more strongly, within conditions);
`section(records, plots, analysis)` -> HTML ("" when no run was perturbed). Every number on the page is in those CSVs.
"""

from __future__ import annotations

import math

import numpy as np

from harness import probes
from harness.analysis import predictors as P
from harness.analysis import robustness as R
from harness.report import html as H
from harness.report.figures_file import markdown_table
from harness.verdicts import CellVerdict, GateVerdict

DETECTABLE_DROP = "detectable drop"  # a cell's smallest drop its pairs could show as a break (docs/glossary.md)
EPISODE_COLUMNS = ("run", "task", "condition", "level", "seed", "episode", "status", "success", "nuisance_mass",
                   "distractor_mass", "background_mass", "target_lift", "nuisance_start", "nuisance_content",
                   "target_lift_content", "nuisance_start_content", "nuisance_reliance", "background_reliance",
                   "distractor_reliance", "nuisance_reliance_start")


def analyse(records, margin: float = R.MARGIN):
    """(episode rows, step-0 shifts, notes, success rows, association rows, paired rows, predictor rows), or None when
    no run was perturbed: one read of every perturbed episode's attention, shared by the report's tables and section.
    `margin`: the drop a HOLDS verdict rules out."""
    if not R.is_perturbed(records):
        return None
    rows, shifts, notes = R.collect(records)
    for _, reader in probes.parts("reader"):  # a probe's per-episode measures beside the attention's (nuisance reliance)
        if hasattr(reader, "add_episode_measures"):
            rows, more = reader.add_episode_measures(rows, records)
            notes = notes + more
    return (rows, shifts, notes, R.success_rows(rows), R.association_rows(rows), R.paired_rows(rows, margin=margin),
            P.predictor_rows(rows))


def tables(records, analysis=None) -> dict[str, list]:
    """{csv name: (columns, rows)} (empty when no run was perturbed); `analysis`: analyse(records), if already made."""
    analysis = analysis or analyse(records)
    if analysis is None:
        return {}
    rows, shifts, _, success, association, paired, predictors = analysis
    episodes = [(r.run, r.task, r.condition, r.level, r.seed, r.episode, r.status, r.success, r.nuisance_mass,
                 r.distractor_mass, r.background_mass, r.target_lift, r.nuisance_start, r.nuisance_content,
                 r.target_lift_content, r.nuisance_start_content, r.nuisance_reliance, r.background_reliance,
                 r.distractor_reliance, r.nuisance_reliance_start) for r in rows]
    return {"robustness.csv": (R.SUCCESS_COLUMNS, success), "robustness_episodes.csv": (EPISODE_COLUMNS, episodes),
            "robustness_shift.csv": (R.SHIFT_COLUMNS, shifts),
            "robustness_association.csv": (R.ASSOCIATION_COLUMNS, association),
            "robustness_paired.csv": (R.PAIRED_COLUMNS, [p.row() for p in paired]),
            **({"robustness_predictors.csv": (P.PREDICTOR_COLUMNS, predictors)} if predictors else {})}


def level_plot(task: str, success: list[tuple]) -> bytes:
    """Success rate (Wilson band), target lift and nuisance mass against level, one line per condition."""
    from harness.report.figures import _figure, _png, run_colours

    cells = [s for s in success if s[0] == task]
    conditions = list(dict.fromkeys(s[1] for s in cells))
    colours = run_colours(len(conditions))
    figure = _figure(12, 3.6)
    axes = figure.subplots(1, 3)
    for colour, condition in zip(colours, conditions):
        c = sorted((s for s in cells if s[1] == condition), key=lambda s: s[2])
        levels = [s[2] for s in c]
        axes[0].plot(levels, [s[7] for s in c], "o-", color=colour, label=condition)
        axes[0].fill_between(levels, [s[8] for s in c], [s[9] for s in c], color=colour, alpha=0.15)
        axes[1].plot(levels, [s[13] for s in c], "o-", color=colour)
        axes[2].plot(levels, [s[10] for s in c], "o-", color=colour)
        if any(math.isfinite(s[14]) for s in c):  # content-only (runs with the blank control): dashed
            axes[1].plot(levels, [s[15] for s in c], "s--", color=colour, alpha=0.7)
            axes[2].plot(levels, [s[14] for s in c], "s--", color=colour, alpha=0.7)
    content = any(math.isfinite(s[14]) for s in cells)
    suffix = " (solid raw, dashed content only)" if content else " (raw map)"
    for ax, title in zip(axes, ("success rate (Wilson 95%)", "target lift (last layer)" + suffix,
                                "nuisance mass (last layer)" + suffix)):
        ax.set_xlabel("level")
        ax.set_title(title, fontsize=10)
        ax.set_xticks(range(6))
    axes[0].set_ylim(-0.02, 1.02)
    axes[0].legend(fontsize=7, framealpha=0.4)  # see-through: a line at 0 under it stays visible
    figure.suptitle(task)
    figure.tight_layout()
    return _png(figure)


def _paired_cells(drops: dict, s: tuple) -> tuple[str, str, str]:
    """(lost / gained pairs, Holm p, verdict with the drop's upper bound, the smallest drop the cell could detect) of
    the success row `s`'s cell, from `drops` ({(task, run): PairedCell}); dashes for the nominal row (level 0)."""
    p = drops.get((s[0], s[3])) if s[2] else None
    if p is None:
        return ("-", "-", "-", "-")
    detectable = f"{round(100 * p.detectable_drop)}" if math.isfinite(p.detectable_drop) else "none"
    return (f"{p.nominal_only} / {p.perturbed_only}", f"{p.p_holm:.3g}",
            f"{p.verdict} (drop <= {round(100 * p.drop_upper)})", detectable)


def section(records, plots, analysis=None) -> str:
    analysis = analysis or analyse(records)
    if analysis is None:
        return ""
    rows, shifts, notes, success, association, paired, predictors = analysis
    drops = {(p.task, p.run): p for p in paired}
    body = [H.note("Success against perturbation level per condition (level 0 = the nominal run), with Wilson 95% "
                   "bands; target lift and nuisance mass (attention on the background and distractors: neither robot, "
                   "target nor another task object) of the primary camera at the last layer, mean over each "
                   "episode's steps. Numbers: tables/robustness*.csv. " + map_note(records))]
    for note in notes:
        body.append(H.banner(note))
    for task in dict.fromkeys(r.task for r in rows):
        body.append(H.section(task, "", level=3))
        body.append(H.Raw(f"<p>{H.esc(R.verdict_line(task, success, paired))}</p>"))
        if (which := P.predictor_table(task, predictors)):
            body.append(H.note(f"{task}, {P.PREDICTOR_CAPTION}:"))
            body.append(H.table(P.PREDICTOR_HEADER, which, numeric=(6, 7, 8)))
        body.append(plots.add(f"robustness_{H.anchor_id(task)[2:]}", level_plot(task, success), f"robustness {task}",
                              "Success (Wilson band), target lift and nuisance mass against level, per condition."))
        content = R.has_content(rows)
        body.append(H.table(("condition", "level", "run", "success [Wilson 95%]", "errored", "paired: lost / gained",
                             "Holm p", "verdict (drop's upper bound, points)", f"{DETECTABLE_DROP} (points)",
                             *_measure_headers(content)),
                            [(s[1], s[2], s[3], H.Raw(f"{s[6]}/{s[4]} {H.fmt_ci(s[7], s[8], s[9], 2)}"), s[5],
                              *_paired_cells(drops, s), *_measure_cells(s, content))
                             for s in success if s[0] == task],
                            numeric=(1, 4)))
        shift = [x for x in shifts if x[1] == task]
        if shift:
            table = {}
            for run, _, condition, level, _, layer, js, lift in shift:
                table.setdefault((condition, level, layer), []).append((js, lift))
            body.append(H.table(("condition", "level", "layer", "pairs", "step-0 JS (bits), mean", "step-0 lift change, mean"),
                                [(c, lvl, layer, len(v), H.fmt(float(np.mean([a for a, _ in v])), 4),
                                  H.fmt(float(np.nanmean([b for _, b in v])) if any(math.isfinite(b) for _, b in v)
                                        else math.nan, 2))
                                 for (c, lvl, layer), v in sorted(table.items())], numeric=(1, 2, 3)))
    body.append(H.table(("task", "map", "episodes", "seeds", "point-biserial r [Fisher 95%]", "seed-cluster 95%",
                         "nuisance: successes", "failures", "within conditions: r [seed-cluster 95%]",
                         f"first {R.START_STEPS} steps: r [seed-cluster 95%]"),
                        [(a[0], MAP_NAMES[a[16]], a[1], a[9], H.fmt_ci(a[2], a[3], a[4], 2),
                          f"[{H.fmt(a[5], 2)}, {H.fmt(a[6], 2)}]", H.fmt(a[7], 3), H.fmt(a[8], 3),
                          H.fmt_ci(a[13], a[14], a[15], 2), H.fmt_ci(a[10], a[11], a[12], 2)) for a in association],
                        numeric=(2, 3)))
    return H.section("Robustness", "".join(str(b) for b in body), anchor="robustness")


SECTION = "## Robustness"


MAP_NAMES = {"raw": "raw", "content": "content only", "reliance": "nuisance reliance"}


def _measure_headers(content: bool) -> tuple[str, ...]:
    raw = ("target lift", "nuisance mass", "distractor mass")
    if not content:
        return raw
    return ("target lift (raw)", "nuisance mass (raw)", "distractor mass (raw)", "target lift (content only)",
            "nuisance mass (content only)")


def _measure_cells(s: tuple, content: bool, markdown: bool = False) -> tuple[str, ...]:
    """Target lift, nuisance and distractor mass of a success row (raw), then content-only lift and nuisance; in the
    HTML's significant digits or EVAL.md's fixed decimals."""
    values = ((s[13], 2), (s[10], 3), (s[11], 3)) + (((s[15], 2), (s[14], 3)) if content else ())
    return tuple(f"{v:.{d}f}" if markdown else H.fmt(v, d) for v, d in values)


def _controls(record) -> tuple[str, ...]:
    spec = ((record.manifest.get("protocol") or {}).get("policy") or {}).get("attention_controls")
    return tuple(n.strip() for n in spec.split(",")) if isinstance(spec, str) else tuple(spec or ())


def map_note(records) -> str:
    """Which attention map each figure of the section uses: raw maps always; content-only ones (the blank-frame part
    removed) too where runs recorded the blank control. Without it the figures may include position-bound
    attention, and the note says so."""
    if not any(_controls(r) for r in records):
        return ("Target lift, nuisance mass and their association use the raw attention maps: these runs had no "
                "--attention-controls, so the figures may include position-bound attention.")
    blank = [r for r in records if "blank" in _controls(r)]
    if not blank:
        return ("Target lift, nuisance mass and their association use the raw attention maps: these runs recorded "
                "only the mirror control, and the content-only view needs --attention-controls blank, so the figures "
                "may include position-bound attention.")
    note = ("Each figure names its map. Raw: the attention maps at every step (they may include position-bound "
            "attention). Content only: at the control steps (--attention-controls), the map minus what remains on a "
            "blank frame, clipped and renormalised (harness.analysis.position.content_only; docs/phases-and-position.md), "
            "so attention bound to a patch's position, not to what it shows, is left out. Target lift and nuisance "
            "mass are given on both, and the association of nuisance mass with success is computed on both (the "
            "'map' column; 'on the content-only maps' in the sentences).")
    missing = [getattr(r, "name", "?") for r in records if "blank" not in _controls(r)]
    if missing:
        note += (f" Runs without the blank control ({', '.join(missing)}) have no content-only figures and are left "
                 "out of the content-only association.")
    return note


VERDICT_NOTE = ("Verdicts per perturbed cell, paired with the nominal seeds:\n"
                f"- {CellVerdict.BREAKS}: the exact McNemar drop survives Holm over the task's cells.\n"
                f"- {CellVerdict.HOLDS}: a drop over the margin ({{margin}} points) is ruled out. The drop's upper "
                "bound (Newcombe at 1 - 0.05 / cells) is within it, and the exact test of a drop that large rejects "
                f"(compare's {GateVerdict.HELD}).\n"
                f"- {CellVerdict.UNDETERMINED}: neither.\n"
                "- Detectable drop: the smallest drop, in points, that the cell's pairs could show as "
                f"{CellVerdict.BREAKS}.")


def markdown(records, note: str = "", margin: float = R.MARGIN, section: str = SECTION) -> str:
    """The Robustness section as Markdown (EVAL.md): per task a verdict line (at most about 25 words), a table of
    success against level per condition with each cell's verdict, detectable drop, target lift and nuisance mass, the
    association table and, with reliance, which measure predicts failure."""
    analysis = analyse(records, margin)
    if analysis is None:
        raise ValueError("no run here was perturbed: give the runs of a robustness grid")
    rows, _, notes, success, association, paired, predictors = analysis
    drops = {(p.task, p.run): p for p in paired}
    lines = [section, "", note, ""] if note else [section, ""]
    lines += [VERDICT_NOTE.format(margin=round(100 * margin)), "", map_note(records), ""]
    lines += [f"- {n}" for n in notes]
    content = R.has_content(rows)
    measures = _measure_headers(content)
    for task in dict.fromkeys(r.task for r in rows):
        lines += [R.verdict_line(task, success, paired), ""]
        lines += markdown_table(("condition", "level", "success", "Wilson 95%", "paired: lost / gained", "Holm p",
                                 "verdict (drop's upper bound, points)", f"{DETECTABLE_DROP} (points)", *measures),
                                [(s[1], s[2], f"{s[6]}/{s[4]}", f"[{s[8]:.2f}, {s[9]:.2f}]", *_paired_cells(drops, s),
                                  *_measure_cells(s, content, markdown=True)) for s in success if s[0] == task])
        lines += ["", f"{task}: nuisance {'mass and reliance' if R.has_reliance(rows) else 'mass'} against success.", "",
                  *markdown_table(R.ASSOCIATION_HEADER, R.association_table(task, association)), ""]
        if (which := P.predictor_table(task, predictors)):
            lines += [f"{task}, {P.PREDICTOR_CAPTION}:", "", *markdown_table(P.PREDICTOR_HEADER, which), ""]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    import argparse
    import functools

    from harness.report.eval_md import section_main

    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--margin", type=float, default=R.MARGIN)
    parser.add_argument("--section", default=SECTION[3:])
    known, rest = parser.parse_known_args(argv)
    section = f"## {known.section}"
    options = (("--margin", f"{known.margin:g}") if known.margin != R.MARGIN else ()) + \
        (("--section", known.section) if section != SECTION else ())
    return section_main(rest, "python -m harness.report.robustness", "Write the Robustness section of an EVAL.md "
                        "from grid runs (--margin M: the drop a HOLDS verdict rules out [0.15]; --section "
                        "TITLE: the section's heading, for a second grid [Robustness]).",
                        functools.partial(markdown, margin=known.margin, section=section), options=options)


if __name__ == "__main__":
    raise SystemExit(main())

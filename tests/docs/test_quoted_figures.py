"""Figures the docs and the README quote match the committed files they come from (issue 43 item 5): each quote is
looked up in its source (models/*/EVAL.md), or regenerated from it or from the function that made it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from harness.analysis.paired import detectable_loss

REPO = Path(__file__).resolve().parents[2]
EVAL = "models/octo-reference-robosuite/EVAL.md"

# (page, what the page says, source file, the line of the source it comes from: a regex)
QUOTES = (
    ("README.md", "take Lift from 20/20 to 13/20, Stack from 15/20 to 5/20 and PickPlaceCan from 15/20 to 4/20", EVAL,
     r"^\| camera@image_wrist \| 1 \| 4/20 \| .* \| 11 / 0 \| 0\.000977 \| BREAKS"),
    ("docs/perturbations.md", "| PickPlaceCan | 15/20 | 4/20: 11 lost, 0 gained, p 0.000977, BREAKS |", EVAL,
     r"^\| camera@image_wrist \| 1 \| 4/20 \| .* \| 11 / 0 \| 0\.000977 \| BREAKS"),
    ("docs/perturbations.md", "| Lift | 20/20 | 13/20: 7 lost, 0 gained, Holm p 0.0156, BREAKS", EVAL,
     r"^\| camera@image_wrist \| 1 \| 13/20 \| .* \| 7 / 0 \| 0\.0156 \| BREAKS"),
    ("docs/perturbations.md", "the grid could resolve about 0.34, 0.21 and 0.26", EVAL,
     r"^\| raw map \| r -0\.15 \[-0\.35, \+0\.04\] \| .* \| 0\.34 \| neither shown \|"),
    ("docs/perturbations.md", "masking it takes Lift from 6/6 to 0/6, p = 0.03", EVAL,
     r"^\| Lift \| `mask-all@image_wrist` \| Lift_plain \| 6 \| 6/6 = 1\.00 .* \| 0/6 = 0\.00 .* \| 0\.0312 \|$"),
    ("docs/perturbations.md", "halves Lift in the closed-loop interventions (6/6 -> 3/6, p = 0.25", EVAL,
     r"^\| Lift \| `mask-all@image_primary` \| Lift_plain \| 6 \| 6/6 = 1\.00 .* \| 3/6 = 0\.50 .* \| 0\.25 \|$"),
    ("README.md", "(Stack and PickPlaceCan 0/20, Lift 6/20)", EVAL, r"^\| texture \| 3 \| 6/20 \|"),
    ("docs/faithfulness-sanity.md", "1.57 [1.29, 1.84]", EVAL, r"1\.57 \[1\.29, 1\.84\]"),
    ("docs/faithfulness-sanity.md", "0.51-0.75 on Stack", EVAL, r"0\.51-0\.75"),
    ("docs/phases-and-position.md", "Lift 0.50 → 0.01 and 0.59 → 0.01", EVAL,
     r"^\| image_primary \| 1 \| target \| 116 \| 0\.59 \| 0\.01 \|$"),  # Lift's position lift table, layer 1
    ("docs/phases-and-position.md", "Stack 0.54 → 0.03 and 0.72 → 0.08", EVAL,
     r"^\| image_primary \| 1 \| target \| 329 \| 0\.72 \| 0\.08 \|$"),
    ("docs/phases-and-position.md", "(layer 3: 1.32 → 1.91)", EVAL,
     r"^\| image_primary \| 3 \| target \| 344 \| 1\.32 \| 1\.91 \|$"),
    ("docs/phases-and-position.md", "(Friedman p = 0.00068, 7 episodes)", EVAL,
     r"^\| gripper \| approach 0\.55, grasp 0\.71, .* release 0\.12 \| Friedman \| 0\.00068 \| 7 \| yes \|$"),
    ("docs/faithfulness.md", "| Lift | wrist | 0.014 / 0.38 | 0.12 / 0.27 | 0.86 / 0.35 | 0.55 [0.5, 0.61] |", EVAL,
     r"^\| image_wrist \| target \| 0\.014 \| 0\.38 \| 40 \| 20 \|$"),
    ("docs/faithfulness.md", "0.55 [0.5, 0.61]", EVAL, r"^\| image_wrist \| 0\.55 \| \[0\.5, 0\.61\] \| 20 \|"),
    ("docs/faithfulness.md", "| PickPlaceCan | wrist | 0.028 / 0.31 | 0.18 / 0.19 | 0.54 / 0.35 |", EVAL,
     r"^\| image_wrist \| target \| 0\.028 \| 0\.31 \| 13\.9 \| 20 \|$"),
    # the early-warning section (issue 74): the readout probe's AUROC at t = 10 and its difference from time and phase
    ("README.md", "AUROC 0.74 (Lift), 0.70 (Stack) and 0.80 (PickPlaceCan), where time and phase give 0.50", EVAL,
     r"^\| readout probe \| 0\.74 \[0\.61, 0\.86\], better \|"),
    ("docs/diagnose.md", "| Lift | 131 of 560 | 0.74 [0.61, 0.86] | 0.50 | t = 10, 25, 50 and 100 (+0.24 [+0.11, +0.36] at t = 10) |",
     EVAL, r"^Lift: better than time and phase: readout probe at t = 10 \(\+0\.24 \[\+0\.11, \+0\.36\]\); readout probe at t = 25 .*readout probe at t = 100"),
    ("docs/diagnose.md", "| Stack | 291 of 560 | 0.70 [0.51, 0.86] | 0.50 | t = 10 only (+0.20 [+0.01, +0.36]) |", EVAL,
     r"^Stack: better than time and phase: readout probe at t = 10 \(\+0\.20 \[\+0\.01, \+0\.36\]\)\.$"),
    ("docs/diagnose.md", "| PickPlaceCan | 225 of 560 | 0.80 [0.57, 0.92] | 0.50 | t = 10 and 25 (+0.30 [+0.07, +0.42] at t = 10) |",
     EVAL, r"^PickPlaceCan: better than time and phase: readout probe at t = 10 \(\+0\.30 \[\+0\.07, \+0\.42\]\); readout probe at t = 25 \([^)]*\)\.$"),
    ("docs/diagnose.md", "| 0.70 [0.51, 0.86] | 0.50 |", EVAL, r"^\| readout probe \| 0\.70 \[0\.51, 0\.86\], better \|"),
    ("docs/diagnose.md", "| 0.80 [0.57, 0.92] | 0.50 |", EVAL, r"^\| readout probe \| 0\.80 \[0\.57, 0\.92\], better \|"),
    ("docs/diagnose.md", "with a median lead of -60 steps on Lift, -86 on Stack and -50 on", EVAL,
     r"^\| readout probe \| 194/225 \(86%\) \| -50\.0 \|"),
    ("docs/diagnose.md", "125 of Lift's 131 failures, 188 of Stack's 291", EVAL,
     r"^\| approach \| 188 \| 0 \| 29 \|"),
)


@pytest.mark.parametrize("page, quote, source, pattern", QUOTES, ids=[q[1][:40] for q in QUOTES])
def test_a_quoted_figure_is_in_its_source(page, quote, source, pattern):
    text = (REPO / page).read_text()
    assert quote in text, f"{page} no longer quotes {quote!r}: update QUOTES with what it says now"
    assert re.search(pattern, (REPO / source).read_text(), re.M), f"{page} quotes {quote!r}, which {source} does not hold"


def test_the_detectable_drop_the_docs_quote_is_the_tests():
    """'no drop of 55 points or more' at 20 pairs, Holm over the primary grid's 27 cells (README,
    docs/perturbations.md; EVAL.md's "detectable drop (points)" column)."""
    assert detectable_loss(20, 0.05, 27) == 11  # 11 of 20 pairs: 55 points
    section = (REPO / EVAL).read_text().split("\n## Robustness\n")[1].split("\n## ")[0]
    assert re.search(r"^\| texture \| 5 \| .* \| 55 \| [\d.]+ \| [\d.]+ \| [\d.]+ \|$", section, re.M)
    for page in ("README.md", "docs/perturbations.md"):
        assert "no drop of 55 points or more" in (REPO / page).read_text()


def test_the_association_resolution_the_readme_quotes_is_the_grids():
    """'the intervals resolve |r| of about 0.11-0.16': half the width of every seed-cluster interval in EVAL.md's
    Robustness section that holds 0."""
    section = (REPO / EVAL).read_text().split("\n## Robustness\n")[1].split("\n## ")[0]  # that section only
    intervals = [(float(low), float(high)) for rows in associations(section).values() for _, low, high in rows.values()]
    halves = [(b - a) / 2 for a, b in intervals if a <= 0 <= b]
    assert len(halves) >= 3
    quoted = f"{min(halves):.2f}-{max(halves):.2f}"
    readme = (REPO / "README.md").read_text().replace("\\|", "|")  # a table cell escapes its pipes
    assert f"|r| of about {quoted}" in readme, quoted


# a row of a task's "nuisance mass against success" table in EVAL.md's Robustness section (harness.report): map,
# measure, over, r, interval
ASSOCIATION = re.compile(r"^\| raw \| nuisance mass \| (episodes|within conditions|first 10 steps) \| ([-+]\d\.\d\d) \| "
                         r"\[([-+.\d]+), ([-+.\d]+)\] \|")


def associations(section: str) -> dict[str, dict[str, tuple[str, str, str]]]:
    """{task: {over: (r, low, high)}} from the section's association tables, each under "<Task>: nuisance mass ..."."""
    out: dict[str, dict[str, tuple[str, str, str]]] = {}
    task = None
    for line in section.splitlines():
        m = re.match(r"^(\w+): nuisance mass against success\.$", line)
        if m:
            task = m.group(1)
            continue
        m = ASSOCIATION.match(line)
        if m and task:
            out.setdefault(task, {})[m.group(1)] = m.groups()[1:]
    return out


def test_the_readme_names_the_r_its_association_finding_rests_on():
    """The finding 'not found to go with failure, except ... Stack' holds for the within-conditions r (centred per
    run) of EVAL.md's Robustness section, not for the pooled one (PickPlaceCan's pooled interval lies below 0): the
    row says which r it means and quotes each task's within-conditions r with its interval (issue 71 item 5.6)."""
    section = (REPO / EVAL).read_text().split("\n## Robustness\n")[1].split("\n## ")[0]
    tables = associations(section)
    assert set(tables) == {"Lift", "Stack", "PickPlaceCan"}
    tasks = {task: (*rows["episodes"], *rows["within conditions"]) for task, rows in tables.items()}
    row = next(line for line in (REPO / "README.md").read_text().splitlines() if "nuisance attention" in line)
    assert "Within conditions (r centred per run" in row and "not found to go with failure" in row
    for task, (_, _, _, r, low, high) in tasks.items():
        assert f"{r} [{low}, {high}]" in row, task
        assert float(high) >= 0, task  # no within-conditions interval lies below 0: none goes with failure
        assert (float(low) > 0) == (task == "Stack"), task  # only Stack's lies above 0, "it goes with success"
    pooled_r, pooled_low, pooled_high = tasks["PickPlaceCan"][:3]
    assert float(pooled_high) <= 0 and f"Pooled over conditions, PickPlaceCan's r is {pooled_r} [{pooled_low}, {pooled_high}]" in row

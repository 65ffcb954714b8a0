"""The report's Grounding section (LIBERO-Object runs): which object the policy picked against the one the instruction
names (own instruction, paraphrases, swaps, nonsense), and attention on the named object against the others per task
and layer (harness.analysis.grounding).

`tables(records)` -> {"grounding_lift.csv", "grounding_objects.csv", "grounding_swap.csv"} (empty without
LIBERO-Object runs); `section(records)` -> HTML; `markdown(records)` -> EVAL.md's
"## Language grounding" section (`python -m harness.report.grounding RUN... --eval-md EVAL.md` writes it). Every number on the page is in those CSVs.
"""

from __future__ import annotations

import math

from harness.analysis import grounding as G
from harness.report import html as H

SECTION = "## Language grounding"


def _analyse(records):
    rows, notes = G.collect(records)
    summary, per_object = G.lift_rows(rows)
    return rows, notes, summary, per_object, G.swap_rows(rows)


def tables(records) -> dict[str, tuple]:
    """{csv name: (columns, rows)} (empty without LIBERO-Object runs)."""
    if not G.is_grounding(records):
        return {}
    _, _, summary, per_object, swaps = _analyse(records)
    return {"grounding_lift.csv": (G.LIFT_COLUMNS, summary), "grounding_objects.csv": (G.OBJECT_COLUMNS, per_object),
            "grounding_swap.csv": (G.SWAP_COLUMNS, swaps)}


def _swap_cells(s: tuple) -> list:
    return [s[1], s[2], s[3], H.Raw(f"{s[5]}/{s[4]} {H.fmt_ci(s[6], s[7], s[8], 2)}"), s[9], s[10], s[11],
            H.fmt(s[12], 2) if s[3] == "swap" else ""]


def section(records) -> str:
    if not G.is_grounding(records):
        return ""
    rows, notes, summary, _, swaps = _analyse(records)
    body = [H.note("LIBERO-Object: the object picked (in the basket, else held, at the episode's end) against the object "
                   "the instruction names; 'blind' is the rate a language-blind policy would get on a swap: how often "
                   "this policy, told the scene's own instruction on the same initial states, picked the object the "
                   "swapped instruction names. Lift = attention mass on an object's mask / its area (1 = chance), mean "
                   "over the steps up to the grasp (the first step the gripper closes); 'top at grasp' counts episodes "
                   "whose named object got more mass than every other object at that step. Numbers: "
                   "tables/grounding_*.csv.")]
    for note in notes:
        body.append(H.banner(note))
    if swaps:
        body.append(H.section("Which object was picked", "", level=3))
        body.append(H.table(("task (scene)", "instruction", "kind", "picked the named object [Wilson 95%]",
                             "picked the scene's target", "picked another", "picked none", "blind"),
                            [_swap_cells(s) for s in swaps], numeric=(4, 5, 6)))
    primary = [s for s in summary if s[2] == "image_primary"]
    if primary:
        body.append(H.section("Named object vs the others (primary camera)", "", level=3))
        body.append(H.table(("task", "layer", "episodes", "named lift", "others: mean lift", "others: max lift",
                             "named / others", "top at grasp"),
                            [(s[1], s[3], s[4], H.fmt(s[5], 2), H.fmt(s[6], 2), H.fmt(s[7], 2), H.fmt(s[8], 2),
                              f"{s[9]}/{s[10]}") for s in primary], numeric=(1, 2)))
    if not swaps and not primary:
        body.append(H.absent("no finished LIBERO-Object episode with object masks"))
    return H.section("Grounding", "".join(str(b) for b in body), anchor="grounding")


def _fmt(x: float, digits: int = 2) -> str:
    return f"{x:.{digits}f}" if isinstance(x, (int, float)) and math.isfinite(x) else "n/a"


def markdown(records, note: str = "") -> str:
    if not G.is_grounding(records):
        raise ValueError("no run here holds LIBERO-Object episodes: give the runs of scripts/evaluate_libero_reference.sh")
    rows, notes, summary, _, swaps = _analyse(records)
    lines = [SECTION, ""] + ([note, ""] if note else []) + [f"- {n}" for n in notes]
    lines += ["### Which object was picked", "",
              "| scene (task) | instruction | kind | picked the named object | Wilson 95% | scene's target | another | "
              "none | blind |", "|---|---|---|---|---|---|---|---|---|"]
    for s in swaps:
        lines.append(f"| {s[1]} | {s[2]} | {s[3]} | {s[5]}/{s[4]} | [{_fmt(s[7])}, {_fmt(s[8])}] | {s[9]} | {s[10]} | "
                     f"{s[11]} | {_fmt(s[12]) if s[3] == 'swap' else ''} |")
    lines += ["", "### Named object vs the others (primary camera, lift up to the grasp)", "",
              "| task | layer | episodes | named lift | others: mean | others: max | named / others | top at grasp |",
              "|---|---|---|---|---|---|---|---|"]
    for s in summary:
        if s[2] == "image_primary":
            lines.append(f"| {s[1]} | {s[3]} | {s[4]} | {_fmt(s[5])} | {_fmt(s[6])} | {_fmt(s[7])} | {_fmt(s[8])} | "
                         f"{s[9]}/{s[10]} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    from harness.report.eval_md import section_main

    return section_main(argv, "python -m harness.report.grounding",
                        "Write the Language grounding section of an EVAL.md from LIBERO-Object runs.", markdown)


if __name__ == "__main__":
    raise SystemExit(main())

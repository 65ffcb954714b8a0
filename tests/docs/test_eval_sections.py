"""No results section of models/*/EVAL.md is edited by hand (issue 67 item 6): each is rendered from a figures
file committed beside the model, and rendering it again gives the committed text; a section whose runs were not kept and
that has no figures file says so in one line (reference_policies.evaluate.NOT_KEPT). No simulation: JSON in, text out."""

from __future__ import annotations

import difflib
import json
from pathlib import Path

import pytest

from harness.analysis.provenance import PROVENANCE_LINE
from reference_policies.evaluate import FIGURES, NOT_KEPT, render

REPO = Path(__file__).resolve().parents[2]
MODELS = sorted(p.parent for p in REPO.glob("models/*/EVAL.md"))


def _top_and_sections(path: Path) -> tuple[str, list[tuple[str, str]]]:
    """EVAL.md -> (its top section's text, [(## heading, body)])."""
    top, _, rest = path.read_text().partition("\n## ")
    sections = []
    for chunk in ("## " + rest).split("\n## ") if rest else []:
        heading, _, body = chunk.partition("\n")
        sections.append(("## " + heading.removeprefix("## "), body))
    return top, sections


def test_every_model_with_an_evaluation_has_its_figures_file():
    assert MODELS, "no models/*/EVAL.md found"
    for model in MODELS:
        assert (model / FIGURES).is_file(), f"{model.name}: EVAL.md without {FIGURES}"


@pytest.mark.parametrize("model", MODELS, ids=lambda p: p.name)
def test_the_top_section_is_rendered_from_its_figures_file(model):
    data = json.loads((model / FIGURES).read_text())
    top, _ = _top_and_sections(model / "EVAL.md")
    rendered = render(data)
    diff = "\n".join(difflib.unified_diff(rendered.strip().splitlines(), top.strip().splitlines(),
                                          f"rendered from {FIGURES}", "committed EVAL.md", lineterm=""))
    assert rendered.strip() == top.strip(), (f"{model.name}/EVAL.md's top section differs from what {FIGURES} renders "
                                             "(edit the figures file or re-run its command, then "
                                             f"reference_policies.evaluate.rerender):\n{diff}")
    # every number of the figures is in the text: each task's counts, rate, interval and each camera's lifts
    for row in data["tasks"]:
        cells = [row["task"], str(row["n"]), str(row["successes"]), f"{row['rate']:.0%}",
                 f"[{row['ci_low']:.2f}, {row['ci_high']:.2f}]", f"{row['seeds'][0]}..{row['seeds'][1]}"]
        assert "| " + " | ".join(cells) + " |" in top, row["task"]
        for camera, lifts in row["target_lift"].items():
            assert f"| {camera} | " + " | ".join(f"{x:.2f}" for x in lifts) + " |" in top, (row["task"], camera)
    assert PROVENANCE_LINE.search(data["provenance"]), "the figures file's provenance line is not in the checked form"


@pytest.mark.parametrize("model", MODELS, ids=lambda p: p.name)
def test_a_section_without_a_figures_file_says_so_in_one_line(model):
    _, sections = _top_and_sections(model / "EVAL.md")
    for heading, body in sections:
        assert body.count(NOT_KEPT) == 1, (f"{model.name}/EVAL.md {heading!r}: no figures file renders it, so it "
                                           f"says once: {NOT_KEPT!r}")


def test_the_figures_render_the_verdict_line_and_the_table(tmp_path):
    """The renderer on two made-up tasks: the average, its interval and the lowest task in one short line."""
    rows = [{"task": t, "n": 10, "successes": s, "rate": s / 10, "ci_low": 0.1, "ci_high": 0.9, "seeds": [0, 9],
             "target_lift": {"image_primary": [1.0, 1.5]}} for t, s in (("Lift", 9), ("Stack", 4))]
    data = {"title": "m", "provenance": "Provenance: command `x`; commit `abcdef1`; machine: CPU.", "note": "N.",
            "tasks": rows}
    text = render(data)
    verdict = next(line for line in text.splitlines() if line.startswith("Average"))
    assert verdict == ("Average over the 2 tasks: **65.0%** (13/20 episodes, Wilson 95% [0.43, 0.82]). "
                       "Lowest task: Stack at 40%.")
    assert len(verdict.split()) <= 25
    assert "| Stack | 10 | 4 | 40% | [0.10, 0.90] | 0..9 | image_primary | 1.00 | 1.50 |" in text
    assert text.splitlines()[2] == data["provenance"]

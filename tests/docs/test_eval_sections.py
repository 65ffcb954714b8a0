"""No results section of models/*/EVAL.md is edited by hand (issue 67 item 6): each is rendered from a figures
file committed beside the model (the top section from eval.json, each "## " section from figures/<section>.json), and
rendering it again gives the committed text; a section whose runs were not kept and that has no figures file says so
in one line (reference_policies.evaluate.NOT_KEPT). No simulation: JSON in, text out."""

from __future__ import annotations

import difflib
import json
import re
from pathlib import Path

import pytest

from harness.analysis.provenance import PROVENANCE_LINE
from harness.report import figures_file
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
def test_each_section_is_rendered_from_its_figures_file_or_says_it_has_none(model):
    _, sections = _top_and_sections(model / "EVAL.md")
    headings = [h for h, _ in sections]
    for heading, body in sections:
        path = figures_file.path_for(model / "EVAL.md", heading)
        if not path.is_file():
            assert body.count(NOT_KEPT) == 1, (f"{model.name}/EVAL.md {heading!r}: no figures file renders it, so it "
                                               f"says once: {NOT_KEPT!r}")
            continue
        doc = figures_file.read(path)
        committed = f"{heading}\n{body}".rstrip("\n") + "\n"
        assert doc["section"] == heading and figures_file.render(doc) == committed, (
            f"{model.name}/EVAL.md {heading!r} differs from what {path.name} renders: run its command again")
        assert NOT_KEPT not in body and PROVENANCE_LINE.search(doc["provenance"])
    for path in sorted((model / figures_file.FIGURES_FOLDER).glob("*.json")):  # no figures file without its section
        assert figures_file.read(path)["section"] in headings, f"{path}: its section is not in EVAL.md"


def test_every_committed_section_round_trips_through_a_figures_document():
    """The figures document keeps every line of a generated section: the committed sections (tables, verdict lines,
    notes, sub-headings) each render back to their own text, blank lines between blocks made one."""
    sections = [(heading, body) for model in MODELS for heading, body in _top_and_sections(model / "EVAL.md")[1]]
    assert len(sections) >= 10
    tables = 0
    for heading, body in sections:
        text = f"{heading}\n\n{body.strip(chr(10))}\n"
        doc = figures_file.figures(text, "Provenance: p.")
        tables += sum("table" in b for b in doc["blocks"])
        expected = re.sub(r"\n[ \t]*\n(?:[ \t]*\n)*", "\n\n", f"{heading}\n\nProvenance: p.\n\n{body.strip(chr(10))}\n")
        assert figures_file.render(json.loads(json.dumps(doc))) == expected, heading
    assert tables >= 20  # the tables are kept as rows of cells (the figures), not as text


def test_a_figures_file_that_is_torn_or_not_one_is_one_line_naming_it(tmp_path):
    bad = tmp_path / "x.json"
    for content in ("{", "[]", json.dumps({"format": 1, "section": "## A", "provenance": "p", "blocks": [1]})):
        bad.write_text(content)
        with pytest.raises(figures_file.FiguresFileError, match=str(bad)) as info:
            figures_file.read(bad)
        assert "\n" not in str(info.value)


def test_a_table_cell_holding_a_bar_keeps_its_row_as_text():
    text = "## S\n\n| a | b |\n|---|---|\n| `x | y` | 2 |\n"
    doc = figures_file.figures(text, "Provenance: p.")
    assert doc["blocks"] == [{"text": ["| a | b |", "|---|---|", "| `x | y` | 2 |"]}]
    assert figures_file.render(doc) == "## S\n\nProvenance: p.\n\n| a | b |\n|---|---|\n| `x | y` | 2 |\n"


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


MODEL_PAGES = sorted(p for model in MODELS for p in (model / "EVAL.md", model / "README.md") if p.is_file())


@pytest.mark.parametrize("page", MODEL_PAGES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_a_model_pages_commands_run_that_model_and_its_pointers_resolve(page):
    """A command on a model's page runs that model, not another folder (issue 71 item 5.10: the 64 px policy's
    evaluation command ran models/octo-reference-robosuite); its links and anchors resolve, and a README section it
    names by its title is one of the README's headings."""
    from tests.docs.test_docs import broken_links, heading_texts

    text = page.read_text()
    others = sorted(set(re.findall(r"--model (models/[\w.-]+)", text)) - {f"models/{page.parent.name}"})
    assert others == [], f"{page.parent.name}/{page.name} runs {others}"
    assert broken_links(page, REPO) == []
    readme = set(heading_texts((REPO / "README.md").read_text()))
    named = re.findall(r"\bREADME\b[^.()]{0,20}\(\"([^\"]+)\"\)", text)
    assert [title for title in named if title not in readme] == [], page

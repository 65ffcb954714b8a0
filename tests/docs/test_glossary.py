"""docs/glossary.md defines each term of issue 67's list once, and every page that uses one of them links to it.

A definition is a `###` heading of the glossary or the first cell of a row of one of its tables. Pages: README.md
and the guides in docs/ (docs/history/ is a work log and exempt).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.docs.test_docs import link_targets, prose_lines

REPO = Path(__file__).resolve().parents[2]
GLOSSARY = REPO / "docs" / "glossary.md"

# the term as the glossary names it, and how a page is found to use it
TERMS = {
    "target lift": r"target lift", "nuisance mass": r"nuisance mass", "reliance": r"\breliance\b",
    "HELD": r"\bHELD\b", "REGRESSED": r"\bREGRESSED\b", "SUSPECT": r"\bSUSPECT\b", "UNDERPOWERED": r"\bUNDERPOWERED\b",
    "INCOMPLETE": r"\bINCOMPLETE\b", "BREAKS": r"\bBREAKS\b", "HOLDS": r"\bHOLDS\b", "UNDETERMINED": r"\bUNDETERMINED\b",
    "Holm": r"\bHolm\b", "Wilson": r"\bWilson\b", "Newcombe": r"\bNewcombe\b", "McNemar": r"\bMcNemar\b",
    "anytime-valid": r"\banytime[- ]valid", "MoRF and LeRF": r"\b(MoRF|LeRF)\b", "impute fill": r"\bimpute\b",
    "position-bound": r"position-bound",
}


def definitions(text: str) -> list[str]:
    """The glossary's defined names: its ### headings and the first cell of each table row."""
    lines = prose_lines(text)
    names = [m.group(1).strip() for m in (re.match(r"^###\s+(.*)$", l) for l in lines) if m]
    rows = [l.split("|")[1].strip() for l in lines if l.startswith("|") and not re.match(r"^\|\s*(-|verdict|page)", l)]
    return names + rows


def test_each_term_is_defined_once():
    defined = definitions(GLOSSARY.read_text())
    assert [t for t in TERMS if defined.count(t) != 1] == []


def pages() -> list[Path]:
    return [REPO / "README.md", *sorted(p for p in (REPO / "docs").glob("*.md") if p != GLOSSARY)]


@pytest.mark.parametrize("page", pages(), ids=lambda p: str(p.relative_to(REPO)))
def test_a_page_that_uses_a_term_links_to_the_glossary(page):
    text = page.read_text()
    prose = "\n".join(prose_lines(text))
    used = [t for t, pattern in TERMS.items() if re.search(pattern, prose)]
    linked = any(t.partition("#")[0].endswith("glossary.md") for t in link_targets(text))
    assert linked or not used, f"{page.name} uses {used[:4]} but does not link docs/glossary.md"


def test_the_check_sees_a_missing_link(tmp_path):
    assert definitions("### target lift\n\n| verdict | meaning |\n|---|---|\n| HELD | x |\n") == ["target lift", "HELD"]
    assert re.search(TERMS["anytime-valid"], "an anytime-valid test") and not re.search(TERMS["HELD"], "HELDOUT")


def section_definitions(text: str) -> dict[str, list[str]]:
    """{## section of the glossary: the names it defines}; a ### heading may define several ("pass, fail and n/a")."""
    out = {}
    for chunk in re.split(r"\n(?=## )", text)[1:]:
        heading, _, body = chunk.partition("\n")
        names = definitions(body)
        out[heading.removeprefix("## ")] = [n for name in names for n in re.split(r",\s*|\s+and\s+", name)]
    return out


def printed_verdicts() -> dict[str, set[str]]:
    """{glossary section (its heading's start): every verdict string the commands print there}: each vocabulary of
    the verdict family (harness.verdicts.FAMILY) in the section it names, and a robustness grid's two terms."""
    from harness.gate.robustness import NOMINAL
    from harness.report.robustness import DETECTABLE_DROP
    from harness.verdicts import FAMILY

    found: dict[str, set[str]] = {}
    for vocabulary in FAMILY:
        found.setdefault(vocabulary.glossary, set()).update(map(str, vocabulary))
    found["Robustness verdicts"] |= {NOMINAL, DETECTABLE_DROP}
    return found


def test_the_family_holds_every_vocabulary_of_verdicts():
    """Issue 72 item 3: every verdict vocabulary is a subclass of harness.verdicts.VerdictKind listed in FAMILY, and
    no module of harness/ defines a verdict enum outside it (which the glossary check would not see)."""
    import ast

    from harness.verdicts import FAMILY, VerdictKind

    assert set(VerdictKind.__subclasses__()) == set(FAMILY) and len(FAMILY) == len(set(FAMILY))
    sources = {path: path.read_text() for path in sorted((REPO / "harness").rglob("*.py"))
               if path != REPO / "harness" / "verdicts.py"}
    outside = [f"{path.relative_to(REPO)}: {node.name}" for path, text in sources.items()
               if "Enum" in text or "VerdictKind" in text  # parse only the modules that could define one
               for node in ast.walk(ast.parse(text)) if isinstance(node, ast.ClassDef)
               and any(getattr(b, "id", getattr(b, "attr", "")) in ("StrEnum", "Enum", "VerdictKind") for b in node.bases)
               and "verdict" in node.name.lower()]
    assert outside == []


def verdict_rows(text: str) -> dict[str, dict[str, str]]:
    """{## section: {first cell: second cell, backticks removed}} of the glossary's tables."""
    out = {}
    for chunk in re.split(r"\n(?=## )", text)[1:]:
        heading, _, body = chunk.partition("\n")
        rows = [[c.strip().replace("`", "") for c in line.split("|")[1:-1]] for line in prose_lines(body)
                if line.startswith("|") and not re.match(r"^\|\s*(-|verdict|page)", line)]
        out[heading.removeprefix("## ")] = {row[0]: row[1] for row in rows if len(row) > 1}
    return out


def test_a_verdicts_row_in_the_glossary_is_its_one_line_meaning():
    """Each verdict carries its one-line meaning; where its section defines verdicts in a table, the row is that
    meaning (the glossary follows the family, not a second list)."""
    from harness.verdicts import FAMILY, GateVerdict

    sections = verdict_rows(GLOSSARY.read_text())
    for vocabulary in FAMILY:
        (section,) = [s for s in sections if s.startswith(vocabulary.glossary)]
        rows = sections[section]
        if not rows:  # defined in prose under a ### heading (Faithfulness): test_every_verdict_a_command_prints_...
            continue
        assert {str(v): rows.get(str(v)) for v in vocabulary} == {str(v): v.meaning for v in vocabulary}, section
    gate = sections[next(s for s in sections if s.startswith(GateVerdict.glossary))]
    assert list(gate) == list(GateVerdict)  # "listed here worst first": the gate's rank


def test_every_verdict_a_command_prints_is_defined_where_its_command_is():
    """Issue 71 item 5.11: the pre-flight verdicts, the step-0 numerics (IDENTICAL's second meaning, UNKNOWN), DISAGREE,
    the sanity check's pass and fail, 'detectable drop' and 'nominal' among them."""
    sections = section_definitions(GLOSSARY.read_text())
    for start, verdicts in printed_verdicts().items():
        (section,) = [s for s in sections if s.startswith(start)]
        assert sorted(verdicts - set(sections[section])) == [], section


def test_a_verdict_the_sequential_test_gives_names_it():
    """REGRESSED, IMPROVED and HELD come from McNemar's test (compare) or from regress's sequential test."""
    from harness.analysis.sequential import VERDICT_OF

    rows = {row.split("|")[1].strip(): row for row in GLOSSARY.read_text().splitlines() if row.startswith("| ")}
    assert all("sequential" in rows[str(v)] for v in VERDICT_OF.values()), [str(v) for v in VERDICT_OF.values()]


def test_section_definitions_split_a_heading_that_defines_several():
    text = "# G\n\n## A\n\n### pass, fail and n/a\n\ntext\n\n## B\n\n| verdict | meaning |\n|---|---|\n| HELD | x |\n"
    assert section_definitions(text) == {"A": ["pass", "fail", "n/a"], "B": ["HELD"]}

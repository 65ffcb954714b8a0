"""README.md and the guides in docs/ read in short sentences (issue 67 item 7): at most 10% of a page's sentences
over 40 words, and none over 70.

A sentence is counted in prose only: fenced code, tables, headings and HTML comments are left out, each list item
ends a sentence, links count as their text and a code span counts its words. Sentences end at ., ! or ? before a
capital, a code span or a bracket; "e.g." and "i.e." do not end one. A provenance line ("Provenance: command ...;
commit ...; machine: ...") is a record, not prose, and is left out. Pages exempt: docs/history/ (work logs) and
the generated findings pages (models/*/EVAL.md, not under docs/).

A page that cannot meet the limits yet may be listed in NOT_YET with the counts it has. Such a page may not get
worse, and the test fails once it meets the limits, so that it leaves the list: the list only shrinks. It is empty.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.docs.test_docs import prose_lines

REPO = Path(__file__).resolve().parents[2]
LONG, TOO_LONG, SHARE = 40, 70, 0.10

# page: (sentences over 40 words, sentences over 70 words) when the rule came in; these may only go down
NOT_YET: dict[str, tuple[int, int]] = {}  # every guide meets the limits now

ABBREVIATIONS = re.compile(r"\b(e\.g|i\.e|etc|vs|cf)\.", re.I)


def sentences(text: str) -> list[str]:
    """The prose sentences of a Markdown page."""
    units, current = [], []
    for line in prose_lines(text) + [""]:
        s = line.strip()
        item = re.match(r"^([-*+]|\d+\.)\s+", s)
        if not s or s.startswith(("#", "|", "<!--", "![")) or item:
            if current:
                units.append(" ".join(current))
                current = []
            if item:
                current.append(s[item.end():])
            continue
        current.append(s)
    out = []
    for unit in units:
        if unit.startswith("Provenance:"):  # a provenance record (command; commit; machine), not prose
            continue
        unit = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", unit)  # a link counts as its text
        unit = ABBREVIATIONS.sub(lambda m: m.group(1), unit)
        out += [s for s in re.split(r"(?<=[.!?])\s+(?=[A-Z`*(\[])", unit) if s.strip()]
    return out


def lengths(page: Path) -> list[int]:
    return [len(s.split()) for s in sentences(page.read_text())]


def guides() -> list[Path]:
    return [REPO / "README.md", *sorted(p for p in (REPO / "docs").glob("*.md"))]


def name(page: Path) -> str:
    return str(page.relative_to(REPO))


@pytest.mark.parametrize("page", guides(), ids=name)
def test_sentences_are_short(page):
    counts = lengths(page)
    long, too_long = sum(n > LONG for n in counts), sum(n > TOO_LONG for n in counts)
    meets = long <= SHARE * len(counts) and too_long == 0
    if name(page) in NOT_YET:
        before = NOT_YET[name(page)]
        assert not meets, f"{name(page)} now meets the limits: take it out of NOT_YET"
        assert (long, too_long) <= before and long <= before[0] and too_long <= before[1], (
            f"{name(page)}: {long} sentences over {LONG} words and {too_long} over {TOO_LONG}, more than the "
            f"{before} it had; shorten the new ones")
        return
    worst = sorted((s for s in sentences(page.read_text()) if len(s.split()) > LONG), key=lambda s: -len(s.split()))
    assert meets, (f"{name(page)}: {long} of {len(counts)} sentences over {LONG} words (at most {SHARE:.0%}) and "
                   f"{too_long} over {TOO_LONG} (none); the longest: " + " || ".join(worst[:3]))


def test_not_yet_names_existing_guides():
    assert set(NOT_YET) <= {name(p) for p in guides()}


def test_sentences_are_counted_in_prose_only():
    text = ("# A heading that is long but not a sentence at all\n\nOne short sentence. Another, e.g. with `code` in it!"
            "\n\n```bash\nnot counted. At all.\n```\n\n| a table | row. Not counted. |\n\n- an item without a stop\n"
            "- [a link](x.md) counts its text. `a span` starts one.\n<!-- a comment. Not counted. -->\n")
    assert sentences(text) == ["One short sentence.", "Another, e.g with `code` in it!", "an item without a stop",
                               "a link counts its text.", "`a span` starts one."]
    assert [len(s.split()) for s in sentences("word " * 41 + ".\n")] == [42]


def opening(text: str) -> tuple[list[str], bool]:
    """A page's first prose paragraph after its title and breadcrumb, and whether a fenced block comes before its
    first ## heading."""
    before = text.split("\n## ", 1)[0]
    body = [line for line in before.splitlines()[1:] if not line.startswith("[octo-harness](")]
    paragraphs = re.split(r"\n\s*\n", "\n".join(body).strip())
    return paragraphs[0].splitlines(), "```" in before


GUIDES_WITHOUT_EXAMPLE = {"docs/README.md", "docs/glossary.md"}  # the index; the glossary opens with its example inline


@pytest.mark.parametrize("page", [p for p in guides()[1:] if name(p) not in GUIDES_WITHOUT_EXAMPLE], ids=name)
def test_a_guide_opens_with_a_short_summary_and_an_example(page):
    first, example = opening(page.read_text())
    assert not first[0].startswith("```") and len(first) <= 3, f"{name(page)}: open with a summary of 3 lines at most"
    assert example, f"{name(page)}: give a runnable example before the first ## heading"

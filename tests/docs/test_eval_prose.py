"""No prose paragraph of a models/*/EVAL.md is over 120 words (issue 74): a long finding is split, listed or put in a
table, so that a reader can take it in.

A paragraph is a block of lines between blank lines; each list item (nested ones too) is a paragraph of its own, its
continuation lines included. Not prose, and not counted: headings, table rows (lines that start with "|"), fenced
code and HTML comments. A quoted block ("> ...") and the "Provenance:" and "Figures file:" lines are prose and
counted. Words are whitespace-separated tokens, a link counting as its text.

No section is exempt: the three Robustness sections of models/octo-reference-robosuite/EVAL.md, hand-kept
until session 33, are now rendered from their figures files.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.docs.test_docs import prose_lines

REPO = Path(__file__).resolve().parents[2]
LIMIT = 120  # words in one prose paragraph or list item
ITEM = re.compile(r"^\s*(?:[-*+]|\d+[.)])\s+")
HEADING = re.compile(r"^ {0,3}(#{1,6})\s")
LINK = re.compile(r"!?\[([^\]]*)\]\([^)]*\)")


def words(paragraph: str) -> int:
    return len(LINK.sub(r"\1", paragraph).split())


def paragraphs(text: str) -> list[tuple[str, str, str]]:
    """The prose paragraphs of a Markdown page: (its "## " section, its nearest heading, the paragraph on one line)."""
    out: list[tuple[str, str, str]] = []
    section = heading = ""
    current: list[str] = []
    comment = False

    def close() -> None:
        if current:
            out.append((section, heading, " ".join(current)))
            current.clear()

    for line in prose_lines(text):  # fenced code comes back as blank lines
        s = line.strip()
        if comment or s.startswith("<!--"):
            close()
            comment = "-->" not in s
            continue
        m = HEADING.match(line)
        if m:
            close()
            heading = s
            if len(m.group(1)) <= 2:
                section = s if len(m.group(1)) == 2 else ""
            continue
        if not s or s.startswith("|"):  # a blank line or a table row ends a paragraph
            close()
            continue
        item = ITEM.match(line)
        if item:  # a list item starts a paragraph of its own
            close()
            s = line[item.end():].strip()
        current.append(s.lstrip("> ").strip() if s.startswith(">") else s)
    close()
    return out


def too_long(page: str, text: str) -> list[str]:
    """'page, section: N words: the paragraph's start' for each prose paragraph over the limit."""
    found = []
    for section, heading, paragraph in paragraphs(text):
        n = words(paragraph)
        if n <= LIMIT:
            continue
        where = section or "(top)"
        if heading and heading != section:
            where += f" > {heading}"
        found.append(f"{page}, {where}: {n} words: {paragraph[:80]}...")
    return found


PAGES = sorted(REPO.glob("models/*/EVAL.md"))


def name(page: Path) -> str:
    return str(page.relative_to(REPO))


def test_there_are_pages_to_check():
    assert len(PAGES) >= 3


@pytest.mark.parametrize("page", PAGES, ids=name)
def test_no_prose_paragraph_of_an_eval_md_is_over_the_limit(page):
    found = too_long(name(page), page.read_text())
    assert found == [], (f"prose paragraphs over {LIMIT} words (split them, list them or make them a table):\n"
                         + "\n".join(found))


def test_the_counter_counts_list_items_and_skips_tables_code_and_headings():
    item, table_words = " ".join(["word"] * 121), " ".join(["cell"] * 300)
    text = (f"# Title\n\n## A section\n\nA short paragraph\nover two lines.\n\n- {item}\n- a short item\n  that goes on.\n"
            f"\n| {table_words} |\n|---|\n| x |\n\n### {' '.join(['heading'] * 130)}\n\n```\n{table_words}\n```\n"
            "<!-- a comment\nover lines -->\n> a quoted\n> block\n")
    got = paragraphs(text)
    assert [(s, h, words(p)) for s, h, p in got] == [
        ("## A section", "## A section", 6), ("## A section", "## A section", 121),
        ("## A section", "## A section", 6), ("## A section", "### " + " ".join(["heading"] * 130), 3)]
    assert got[2][2] == "a short item that goes on." and got[3][2] == "a quoted block"
    found = too_long("x/EVAL.md", text)
    assert len(found) == 1 and found[0].startswith("x/EVAL.md, ## A section: 121 words: word word")
    # a 300-word table is not prose; a 120-word item is at the limit; a link counts as its text
    assert too_long("x/EVAL.md", f"## S\n\n| {table_words} |\n|---|\n\n- {' '.join(['w'] * 120)}\n") == []
    assert words("[three linked words](../../docs/a-long-target.md#anchor) and two") == 5


def test_a_paragraph_that_follows_a_table_row_is_its_own():
    text = "## S\n\n| a | b |\n|---|---|\n| 1 | 2 |\nA line right under the table.\n- an item\n"
    assert [p for _, _, p in paragraphs(text)] == ["A line right under the table.", "an item"]

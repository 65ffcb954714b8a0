"""The figures file of a results section (issue 67 item 6).

A command that writes a section of a model's EVAL.md first writes the section's figures to
`<model>/figures/<section>.json`, then renders the section from that file:

    doc = figures(section_markdown, provenance)   # {"format", "section", "provenance", "blocks": [...]}
    path = write(eval_md, doc)                    # <eval_md's folder>/figures/<slug>.json, atomically
    text = render(read(path))                     # the section as EVAL.md holds it

Each table is kept as its header and rows of cells (as printed: the figures), each verdict line or note as its text
lines. tests/docs/test_eval_sections.py renders every section again from its file and compares it with the committed
EVAL.md, so a section cannot be edited by hand. A section whose runs were not kept has no file and says so in one line.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from harness.files import FIGURES_FOLDER, atomic_write_json

FORMAT = 1
_RULE = re.compile(r"^\|(\s*:?-+:?\s*\|)+$")  # a table's header rule: |---|---:|


class FiguresFileError(ValueError):
    """A figures file that cannot be rendered (one line naming the file and what is wrong)."""


def slug(heading: str) -> str:
    """"## Robustness of the wrist camera" -> "robustness-of-the-wrist-camera"."""
    return re.sub(r"[^a-z0-9]+", "-", heading.lstrip("#").strip().lower()).strip("-") or "section"


def path_for(eval_md: str | Path, heading: str) -> Path:
    return Path(eval_md).parent / FIGURES_FOLDER / f"{slug(heading)}.json"


def _cells(line: str) -> list[str] | None:
    """A table row's cells, or None where splitting on " | " would not give the row back (a cell holding "|")."""
    if not (line.startswith("| ") and line.endswith(" |")):
        return None
    cells = line[2:-2].split(" | ")
    return cells if _row(cells) == line else None


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def markdown_table(header, rows, rule: str | None = None) -> list[str]:
    """A Markdown table's lines, as the section generators write them: the header, its rule ('|---' per column
    unless given: alignment) and a line per row, every cell as str()."""
    return [_row([str(c) for c in header]), rule or "|---" * len(header) + "|",
            *(_row([str(c) for c in row]) for row in rows)]


def _block(chunk: str) -> dict:
    lines = chunk.split("\n")
    if len(lines) >= 2 and _RULE.match(lines[1]):
        rows = [_cells(line) for line in [lines[0], *lines[2:]]]
        if all(r is not None and len(r) == len(rows[0]) for r in rows):  # else a cell holds "|": kept as text
            return {"table": {"header": rows[0], "rule": lines[1], "rows": rows[1:]}}
    return {"text": lines}


def figures(section: str, provenance: str) -> dict:
    """A section's Markdown ("## Heading" then its body, without the provenance line) -> its figures document.
    Blank lines between blocks become one."""
    heading, _, body = section.strip("\n").partition("\n")
    if not heading.startswith("#"):
        raise ValueError(f"a section starts with its heading; got {heading[:60]!r}")
    chunks = [c.strip("\n") for c in re.split(r"\n[ \t]*\n", body.strip("\n")) if c.strip()]
    return {"format": FORMAT, "section": heading, "provenance": provenance, "blocks": [_block(c) for c in chunks]}


def render(doc: dict) -> str:
    """The figures document -> the section's Markdown: heading, provenance line, then each block."""
    parts = [doc["section"], doc["provenance"]]
    for block in doc["blocks"]:
        if "table" in block:
            table = block["table"]
            parts.append("\n".join([_row(table["header"]), table["rule"], *(_row(r) for r in table["rows"])]))
        else:
            parts.append("\n".join(block["text"]))
    return "\n\n".join(parts) + "\n"


def write(eval_md: str | Path, doc: dict) -> Path:
    return atomic_write_json(path_for(eval_md, doc["section"]), doc, exact=True)


def read(path: str | Path) -> dict:
    """A figures file, checked enough to render (a torn or edited file is one line naming it)."""
    try:
        doc = json.loads(Path(path).read_text())
        ok = (isinstance(doc, dict) and doc.get("format") == FORMAT and isinstance(doc.get("section"), str)
              and isinstance(doc.get("provenance"), str) and isinstance(doc.get("blocks"), list)
              and all(isinstance(b, dict) and ("table" in b or isinstance(b.get("text"), list)) for b in doc["blocks"]))
    except (OSError, ValueError) as exc:
        raise FiguresFileError(f"{path}: cannot read it as a figures file ({exc})") from None
    if not ok:
        raise FiguresFileError(f"{path}: not a figures file of format {FORMAT} (section, provenance, blocks)")
    return doc

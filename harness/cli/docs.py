"""The docs' option tables, generated from the option fields (harness/options.py): `python -m harness.cli.docs`
rewrites each table between its markers in place; tests/docs/test_option_tables.py checks that they match."""

from __future__ import annotations

import sys
from pathlib import Path

from harness.options import table

ROOT = Path(__file__).resolve().parents[2]
BEGIN = "<!-- generated from the option fields by `python -m harness.cli.docs`: edit the fields, not this table -->\n"
END = "<!-- end of the generated table -->\n"


def tables() -> dict[str, str]:
    """{docs page (relative to the repository): its generated option table}."""
    from harness.run.settings import RUN_OPTIONS

    return {"docs/running.md": table(RUN_OPTIONS)}


def rendered(text: str, generated: str, page: str = "the page") -> str:
    """`text` with the table between the markers replaced by `generated`."""
    if text.count(BEGIN) != 1 or text.count(END) != 1:
        raise ValueError(f"{page} needs exactly one pair of generated-table markers")
    head, rest = text.split(BEGIN)
    return head + BEGIN + generated + END + rest.split(END, 1)[1]


def main() -> int:
    for page, generated in tables().items():
        path = ROOT / page
        text = path.read_text()
        new = rendered(text, generated, page)
        if new != text:
            path.write_text(new)
            print(f"rewrote the option table of {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

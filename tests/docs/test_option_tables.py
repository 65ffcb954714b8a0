"""The docs' option tables are generated from the option fields (issue 42): the table in docs/running.md is exactly
what `python -m harness.cli.docs` writes, so a field added, renamed or re-worded without rewriting it fails here."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from harness.cli.docs import BEGIN, END, ROOT, rendered, tables
from harness.options import option, table


def test_the_docs_option_tables_are_the_fields():
    for page, generated in tables().items():
        text = (ROOT / page).read_text()
        assert rendered(text, generated, page) == text, f"run `python -m harness.cli.docs` to rewrite {page}'s table"
        assert "`--faithfulness-fill mean\\|blur\\|impute`" in generated and "`--ci-method" in generated


def test_a_changed_field_is_a_changed_table():
    """The check above can fail: a field's help text is its row, and a table between markers is replaced whole."""

    @dataclass(frozen=True)
    class Options:
        margin: float = option(0.15, "--margin", "the largest drop that still HOLDS [0.15]", type=float, file=(float,))

    @dataclass(frozen=True)
    class Reworded:
        margin: float = option(0.15, "--margin", "the largest drop a cell may lose [0.15]", type=float, file=(float,))

    page = f"# A page\n\n{BEGIN}{table([(Options, 'protocol')])}{END}\nAfter.\n"
    assert "| `--margin MARGIN` | the largest drop that still HOLDS [0.15] | `protocol.margin` |" in page
    assert rendered(page, table([(Options, "protocol")])) == page
    assert rendered(page, table([(Reworded, "protocol")])) != page
    with pytest.raises(ValueError, match="markers"):
        rendered("# no markers\n", table([(Options, "protocol")]))

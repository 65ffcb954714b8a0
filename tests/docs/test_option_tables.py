"""The docs' option tables are generated from the option fields (issue 42): the table in docs/running.md is exactly
what `python -m harness.cli.docs` writes, so a field added, renamed or re-worded without rewriting it fails here.
Every option of every command shows its own default and names its field (issue 64)."""

from __future__ import annotations

import argparse
import math
import re
from dataclasses import dataclass

import pytest

from harness.cli import build_parser
from harness.cli.docs import BEGIN, END, ROOT, rendered, tables
from harness.options import UNSET, option, options, shown, table

BRACKET = re.compile(r"\[([^\]]*)\]$")  # a help's trailing [default]


def _commands() -> dict[str, argparse.ArgumentParser]:
    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def _same(text: str, value, kind) -> bool:
    """The bracket's text read as the flag reads it (int, float, str) is the default."""
    if isinstance(value, float):
        return math.isclose(float(text), value, rel_tol=1e-5)
    if isinstance(value, tuple):
        return tuple(text.split(",")) == tuple(str(v) for v in value)
    return (kind or str)(text) == value if kind in (None, int, str) else text == shown(value)


def test_every_option_of_every_command_shows_its_own_default():
    """A declared option's [default] is its field's (or the command's own, as robustness' 20 episodes): its help
    text states none of its own; where words say what the value means they contain the value. A plain flag's
    [default] shows argparse's default."""
    declared = plain = 0
    for command, parser in _commands().items():
        for action in parser._actions:
            if not action.option_strings or action.help in (None, argparse.SUPPRESS):
                continue
            where = (command, action.option_strings[0])
            bracket = BRACKET.search(action.help)
            o = getattr(action, "declared", None)
            if o is None:
                if action.default not in (None, False, argparse.SUPPRESS):
                    assert bracket and str(action.default) in bracket.group(1).split(" "), where
                    plain += 1
                continue
            declared += 1
            raw = o.text_for(command)
            assert not BRACKET.search(raw or ""), where  # the text states no default: it comes from the field
            default = o.value if action.default is None else action.default
            if o.default_text is not None:  # words for what the value means, with the value in them
                assert bracket is None or shown(default) is None or shown(default) in bracket.group(1), where
            elif o.action == "store_true" or shown(default) is None:
                assert bracket is None, where  # a switch is off unless given; None has no value to show
            else:
                assert bracket and _same(bracket.group(1), default, action.type), where
    assert declared > 60 and plain >= 5  # run, robustness, the gates and sanity: every command was walked


def test_a_flag_names_its_field_or_says_which():
    """--png-every sets png_every; a negated switch (--no-video) or a renamed flag (--intervene) declares it."""
    from harness.gate.config import GateConfig
    from harness.run.settings import RUN_OPTIONS

    seen, own_run_default = set(), []
    for cls in [cls for cls, _ in RUN_OPTIONS] + [GateConfig]:
        for field, o in options(cls):
            if o.absent is not UNSET:
                own_run_default.append(o.flag)
            if o.negated:
                assert o.action == "store_true" and o.key == "no_" + field.name, o.flag
            else:
                assert (o.field or o.key) == field.name, (o.flag, field.name)
                assert o.field is None or o.field != o.key, o.flag  # declared only where the names differ
            seen.add(o.flag)
    assert {"--no-video", "--no-masks", "--intervene", "--task"} <= seen
    # a run's default is the field's (receding steps 4, --bbox off); only masks, which envs.make shares, keep their own
    assert own_run_default == ["--no-masks"]


def test_the_docs_option_tables_are_the_fields():
    for page, generated in tables().items():
        text = (ROOT / page).read_text()
        assert rendered(text, generated, page) == text, f"run `python -m harness.cli.docs` to rewrite {page}'s table"
        assert "`--faithfulness-fill mean\\|blur\\|impute`" in generated and "`--ci-method" in generated


def test_a_changed_field_is_a_changed_table():
    """The check above can fail: a field's help text is its row, and a table between markers is replaced whole."""

    @dataclass(frozen=True)
    class Options:
        margin: float = option(0.15, "--margin", "the largest drop that still HOLDS", type=float, file=(float,))

    @dataclass(frozen=True)
    class Reworded:
        margin: float = option(0.15, "--margin", "the largest drop a cell may lose", type=float, file=(float,))

    @dataclass(frozen=True)
    class Moved:  # a new default is a new [default]: the help never states one of its own
        margin: float = option(0.2, "--margin", "the largest drop that still HOLDS", type=float, file=(float,))

    page = f"# A page\n\n{BEGIN}{table([(Options, 'protocol')])}{END}\nAfter.\n"
    assert "| `--margin MARGIN` | the largest drop that still HOLDS [0.15] | `protocol.margin` |" in page
    assert rendered(page, table([(Options, "protocol")])) == page
    assert rendered(page, table([(Reworded, "protocol")])) != page
    assert "| the largest drop that still HOLDS [0.2] |" in rendered(page, table([(Moved, "protocol")]))
    with pytest.raises(ValueError, match="markers"):
        rendered("# no markers\n", table([(Options, "protocol")]))

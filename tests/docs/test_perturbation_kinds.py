"""The perturbation kinds are one table (envs.perturbations.KIND_TABLE): docs/perturbations.md's kinds table and the
robustness options table, and the `--perturb` help of `run` and `robustness`, list exactly its kinds in its order."""

import re
from pathlib import Path

from envs.perturbations import KEYED_KINDS, KIND_TABLE, KINDS, Kind

ROOT = Path(__file__).resolve().parents[2]
PAGE = (ROOT / "docs" / "perturbations.md").read_text()


def _kinds_table_names() -> list[str]:
    """The first column of the '## Kinds and levels' table."""
    section = PAGE.split("## Kinds and levels", 1)[1].split("\n## ", 1)[0]
    return [m.group(1) for m in re.finditer(r"^\| `([a-z-]+)` \|", section, re.M)]


def test_the_table_is_classes_with_one_name_each():
    assert KINDS == tuple(KIND_TABLE) and len(set(KINDS)) == len(KINDS) >= 7
    assert all(isinstance(kind, Kind) and kind.name == name for name, kind in KIND_TABLE.items())
    assert KEYED_KINDS == ("camera", "noise")


def test_the_docs_kinds_table_lists_the_table():
    assert _kinds_table_names() == list(KINDS)
    row = next(line for line in PAGE.splitlines() if line.startswith("| `--perturb` |"))
    listed = [name.split("@")[0] for name in re.findall(r"`([a-z@A-Z_-]+)`", row.split("|")[2])]
    assert list(dict.fromkeys(listed)) == list(KINDS)
    assert all(f"`{k}@" in row for k in KEYED_KINDS)


def test_the_command_line_help_lists_the_table():
    from harness.cli import build_parser

    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.choices and "run" in a.choices).choices
    run_help = next(a.help for a in subparsers["run"]._actions if "--perturb" in a.option_strings)
    grid_help = next(a.help for a in subparsers["robustness"]._actions if "--perturb" in a.option_strings)
    names = ", ".join(KINDS)
    keyed = " / ".join(f"{k}@KEY" for k in KEYED_KINDS)
    assert f": {names} at level 0 (nominal) to 5; {keyed} pick a camera" in run_help
    assert f"({names}; {keyed} for one camera)" in grid_help

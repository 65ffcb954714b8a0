"""What `--help` says agrees with what the code does (issue 71 item 5): the conventions' defaults are worded from the
family table the code resolves with, in the code's precedence; `--task`'s family name runs what it says; each
fast-render speed-up names its unit (per rendered frame, per env step) wherever it is quoted; no help prints a
literal "%%"."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from harness.cli import build_parser

REPO = Path(__file__).resolve().parents[2]
BRACKET = re.compile(r"\[([^\]]*)\]$")


@pytest.fixture(scope="module")
def parsers() -> dict[str, argparse.ArgumentParser]:
    top = build_parser()
    (sub,) = [a for a in top._actions if isinstance(a, argparse._SubParsersAction)]
    return {"octo-harness": top, **sub.choices}


def help_of(parser: argparse.ArgumentParser, flag: str) -> str:
    """The flag's help as --help prints it (% expanded), unwrapped."""
    (action,) = [a for a in parser._actions if flag in a.option_strings]
    return parser._get_formatter()._expand_help(action)


@pytest.mark.parametrize("key, flag", [("image_convention", "--image-convention"), ("action_space", "--action-space")])
def test_a_conventions_default_is_each_familys_in_the_codes_precedence(parsers, key, flag):
    """`run --help` shows, per task family, the default the run resolves (harness.conventions.resolve_env over the
    family table), after the checkpoint's harness.toml, which wins over it."""
    from envs.options import FAMILY_DEFAULTS, FAMILY_NAMES
    from harness.conventions import CheckpointConventions, resolve_env

    bracket = BRACKET.search(help_of(parsers["run"], flag)).group(1)
    resolved, sources = resolve_env(CheckpointConventions(), {}, list(FAMILY_DEFAULTS))
    for family, options in resolved.items():
        shown = f"{FAMILY_NAMES[family]} {getattr(options, key)}"
        assert shown in bracket and sources[family][key] == f"default:{family}", (flag, shown, bracket)
        assert bracket.index("harness.toml") < bracket.index(shown), bracket
    other = {"image_convention": "opengl", "action_space": "robosuite"}[key]  # no family's default
    with_file, _ = resolve_env(CheckpointConventions(env={key: other}), {}, list(FAMILY_DEFAULTS))
    assert {getattr(o, key) for o in with_file.values()} == {other}  # the checkpoint's file wins over every family


def test_the_camera_help_gives_the_codes_precedence(parsers):
    from harness.conventions import CheckpointConventions, resolve_env

    text = help_of(parsers["run"], "--camera")
    assert text.index("harness.toml") < text.index("task's cameras"), text
    from_file, sources = resolve_env(CheckpointConventions(env={"cameras": {"image_primary": ["agentview", 84]}}),
                                     {}, ["robosuite"])
    assert from_file["robosuite"].cameras == (("image_primary", "agentview", 84),)
    assert sources["robosuite"]["cameras"] == "checkpoint"
    assert resolve_env(CheckpointConventions(), {}, ["robosuite"])[0]["robosuite"].cameras is None  # the task's


def test_the_task_help_names_what_each_family_name_runs(parsers):
    from envs import list_tasks
    from envs.resolver import ROBOSUITE_TASKS, resolve_names
    from harness.cli.tasks import TASK_NAMES_LINE

    robosuite = tuple(t.name for t in list_tasks())
    for name in ROBOSUITE_TASKS:
        assert resolve_names([name]) == robosuite and not any("/" in t for t in robosuite)
    for text in (help_of(parsers["run"], "--task"), TASK_NAMES_LINE):
        assert all(f"'{name}'" in text or f"{name} " in text for name in ROBOSUITE_TASKS), text
        assert "every robosuite task" in text and "registered" not in text, text


SPEEDUP = re.compile(r"about (\d+(?:\.\d+)?)\s?[x×](?: faster)? per (rendered frame|env step)")
ANY_SPEEDUP = re.compile(r"about \d+(?:\.\d+)?\s?[x×]|\d+(?:\.\d+)?\s?[x×] faster")


def _quoted_speedups(parsers) -> list[tuple[str, str]]:
    """(where, text) of every module, page and help that quotes a speed-up, whitespace and string joins unwrapped."""
    texts = []
    for path in sorted([*REPO.glob("envs/**/*.py"), *REPO.glob("harness/**/*.py"), REPO / "README.md",
                        *(REPO / "docs").glob("*.md")]):
        text = re.sub(r'"\s+(f?)"', "", path.read_text()) if path.suffix == ".py" else path.read_text()
        texts.append((str(path.relative_to(REPO)), " ".join(text.split())))
    for command, parser in parsers.items():
        for action in parser._actions:
            if action.help not in (None, argparse.SUPPRESS):
                texts.append((f"{command} {action.option_strings}", parser._get_formatter()._expand_help(action)))
    return [(where, text) for where, text in texts if ANY_SPEEDUP.search(text)]


def test_each_fast_render_speedup_names_its_unit_and_the_units_agree(parsers):
    """'4x' is per rendered frame, '3x' per env step (docs/benchmarks.md: 80 ms, 26 ms with --fast-render); every
    quote says which, and a unit has one figure everywhere."""
    quoted = _quoted_speedups(parsers)
    assert {"envs/render.py", "envs/options.py", "docs/running.md"} <= {w for w, _ in quoted}
    assert any(w.startswith("run ") for w, _ in quoted)  # the --fast-render help
    figures: dict[str, set[str]] = {}
    for where, text in quoted:
        assert len(ANY_SPEEDUP.findall(text)) == len(SPEEDUP.findall(text)), f"{where}: a speed-up without its unit"
        for number, unit in SPEEDUP.findall(text):
            figures.setdefault(unit, set()).add(number)
    assert all(len(numbers) == 1 for numbers in figures.values()), figures
    row = re.search(r"^\| env step, Lift, 256\+128 px cameras \| (\d+) ms .*; (\d+) ms with `--fast-render`\)",
                    (REPO / "docs/benchmarks.md").read_text(), re.M)
    assert figures["env step"] == {str(round(int(row.group(1)) / int(row.group(2))))}


def test_no_help_prints_a_doubled_percent(parsers):
    """argparse %-formats help strings but not a description: '95%%' there prints as written."""
    printed = {name: parser.format_help() for name, parser in parsers.items()}
    assert len(printed) >= 10 and "95% intervals" in printed["sanity"]
    assert [name for name, text in printed.items() if "%%" in text] == []

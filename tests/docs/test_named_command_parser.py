"""The command line builds only the named command's options (harness.cli.build_parser(command)): a command line
naming a command must parse to the same arguments, and fail with the same message, as the whole parser."""

from __future__ import annotations

import contextlib
import io

import pytest

from harness.cli import COMMANDS, _name, build_parser, named_command

LINES = [
    ["tasks"],
    ["run", "--task", "Lift", "--episodes", "2", "--no-video"],
    ["compare", "a", "b"],
    ["report", "somewhere"],
    ["run", "--task", "Lift", "--no-such-option"],  # an unknown option: the same one line
    ["run", "--episodes", "two"],  # a bad value
]


def _parse(parser, argv):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            return vars(parser.parse_args(argv)), None
        except SystemExit as exc:
            return None, (exc.code, err.getvalue())


@pytest.mark.parametrize("argv", LINES, ids=lambda a: " ".join(a))
def test_the_named_commands_parser_parses_as_the_whole_one(argv):
    assert named_command(argv) == argv[0]
    assert _parse(build_parser(argv[0]), argv) == _parse(build_parser(), argv)


def test_every_command_is_named_and_help_or_no_command_needs_the_whole_parser():
    names = [_name(module) for module in COMMANDS]
    assert all(named_command([n, "--x"]) == n for n in names)
    assert named_command(["--debug", names[0]]) == names[0]  # top-level flags take no value
    for argv in ([], ["--help"], ["-h", "run"], ["runn", "--task"], ["--", "run"]):
        assert named_command(argv) is None, argv

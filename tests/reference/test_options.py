"""The reference policies' command lines come from dataclass fields (reference_policies.options): every option of
every command is a field's, its help's [default] is that field's default, and no module adds a flag of its own."""

import argparse
import ast
import dataclasses
from pathlib import Path

import pytest

from harness.options import option, option_of, shown
from reference_policies import dagger, evaluate, libero_eval, libero_pipeline, libero_probe, pipeline
from reference_policies.options import Provenance, Workers, add_options, default_of
from reference_policies.train import TrainConfig

ROOT = Path(__file__).resolve().parents[2]


def closed_loop_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    add_options(parser, (libero_eval.ClosedLoopOptions, Provenance))
    return parser


# command -> (its parser, the dataclasses its options come from, first owner wins a flag)
COMMANDS = {
    "pipeline": (pipeline.command_parser, (pipeline.PipelineOptions, TrainConfig, Workers)),
    "libero_pipeline": (libero_pipeline.command_parser, (libero_pipeline.LiberoPipelineOptions, TrainConfig, Workers)),
    "libero_probe": (libero_probe.command_parser, (libero_probe.ProbeOptions, Workers)),
    "dagger": (dagger.command_parser, (dagger.DaggerOptions, dagger.DaggerConfig, Workers)),
    "evaluate": (evaluate.command_parser, (evaluate.EvaluateOptions, Provenance)),
    "libero_eval closed-loop": (closed_loop_parser, (libero_eval.ClosedLoopOptions, Provenance)),
}


def disagreements(parser: argparse.ArgumentParser, classes) -> list[str]:
    """Every way an option of `parser` departs from the field that declares it: no field, an argparse default of its
    own, a help whose [default] is not the field's (or that writes one the field's default would add)."""
    fields = {}
    for cls in classes:
        for field in dataclasses.fields(cls):
            if option_of(field) is not None:
                fields.setdefault(option_of(field).flag, field)
    found = []
    one_of = [a for g in parser._mutually_exclusive_groups if g.required for a in g._group_actions]
    for action in parser._actions:
        flags = [s for s in action.option_strings if s.startswith("--") and s != "--help"]
        if not flags:
            continue
        field = fields.get(flags[0])
        if field is None:
            found.append(f"{flags[0]}: no dataclass field declares it")
            continue
        o, default = option_of(field), default_of(field)
        if action.default is not None:
            found.append(f"{flags[0]}: argparse default {action.default!r} beside the field's")
        if (o.text_for("run") or "").endswith("]"):
            found.append(f"{flags[0]}: its help writes its own [default]")
        if o.action == "store_true" or default is dataclasses.MISSING or action in one_of:
            continue  # a switch, a required option, one of a required choice: nothing is left to a default
        expected = o.shown("run")
        if expected is None:
            found.append(f"{flags[0]}: not given means what? (a None or '' default without default_text)")
        elif not action.help.endswith(f"[{expected}]") or (default not in (None, "") and expected != shown(default)):
            found.append(f"{flags[0]}: help {action.help!r} does not end with the field's default [{shown(default)}]")
    return found


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_option_is_a_field_and_its_help_shows_the_fields_default(command):
    make, classes = COMMANDS[command]
    parser = make()
    assert len([a for a in parser._actions if a.option_strings]) >= 3
    assert disagreements(parser, classes) == []


def test_the_check_sees_a_copied_default_and_a_flag_of_no_field():
    @dataclasses.dataclass(frozen=True)
    class Copied:
        steps: int = option(6000, "--steps", "training steps [5000]", type=int)

    parser = argparse.ArgumentParser()
    add_options(parser, (Copied,))
    parser.add_argument("--loose", default=3)
    assert disagreements(parser, (Copied,)) == ["--steps: its help writes its own [default]",
                                                "--loose: no dataclass field declares it"]


def test_no_module_adds_a_flag_of_its_own():
    """Positional arguments (run folders) are no options; every `--flag` comes from a field."""
    own = []
    for path in sorted((ROOT / "reference_policies").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument" and node.args \
                    and isinstance(node.args[0], ast.Constant) and str(node.args[0].value).startswith("-"):
                own.append(f"{path.name}:{node.lineno} {node.args[0].value}")
    assert own == []


def test_no_option_given_is_every_fields_default():
    args = pipeline.command_parser().parse_args([])
    from reference_policies.options import values

    assert TrainConfig(**values(TrainConfig, args)) == TrainConfig()
    assert pipeline.PipelineOptions(**values(pipeline.PipelineOptions, args)) == pipeline.PipelineOptions()
    given = libero_pipeline._checked(libero_pipeline.command_parser(), [])[0]
    assert (given.steps, given.batch_size, given.workers) == (libero_pipeline.RECIPE_STEPS["second"],
                                                              TrainConfig().batch_size, Workers().workers)


@pytest.mark.parametrize("flags,words", [(["--steps", "0"], "steps and batch size must be >= 1"),
                                         (["--learning-rate", "-1"], "the learning rate >= 0"),
                                         (["--workers", "0"], "--workers 0: give 1 or more processes"),
                                         (["--episodes", "3"], "--episodes must be >= 4")])
def test_a_value_its_field_refuses_is_one_line_and_exit_2(flags, words, capsys):
    with pytest.raises(SystemExit) as exit_info:
        pipeline.main([*flags, "--out", "/nonexistent/x", "--data", "/nonexistent/d"])
    assert exit_info.value.code == 2
    (line,) = [text for text in capsys.readouterr().err.splitlines() if "error:" in text]
    assert words in line

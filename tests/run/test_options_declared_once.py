"""Each option declared once (issue 42): the `run` and `robustness` parsers, the protocol file's keys and the manifest's
record come from the option fields; every `run` flag that changes a file is a field recorded in the manifest; the
shared flags are declared in one place each; adding an option is one field."""

from __future__ import annotations

import argparse
import ast
import dataclasses
from dataclasses import dataclass
from pathlib import Path

from harness.cli import build_parser
from harness.options import add_arguments, file_keys, given, option, options, record, table
from harness.run.settings import FILE_KEYS, RUN_OPTIONS

HARNESS = Path(__file__).resolve().parents[2] / "harness"
# `run` flags that are no field: they choose what the command does with the folder, where episodes execute and
# where they render, and the live viewer; none changes a file of the run (render device: recorded in platform.gl)
RUN_CONTROL = {"--protocol", "--resume", "--overwrite", "--retry-failed", "--verbose", "--workers", "--executor",
               "--ray-address", "--policy-replicas", "--render-device", "--viewer-port", "--web-port"}


def _subparser(name: str) -> argparse.ArgumentParser:
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return sub.choices[name]


def _flags(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {a.option_strings[0]: a for a in parser._actions if a.option_strings and a.option_strings[0] != "-h"}


def test_every_run_flag_that_changes_a_file_is_a_recorded_field():
    fields = {o.flag: o for cls, _ in RUN_OPTIONS for _, o in options(cls)}
    flags = _flags(_subparser("run"))
    assert set(flags) - RUN_CONTROL == set(fields)  # no flag outside the fields but the control flags
    assert all(fields[f].file for f in fields)  # and each one a protocol-file key
    assert FILE_KEYS == file_keys(*(cls for cls, _ in RUN_OPTIONS))
    assert {"faithfulness_fill", "ci_method", "camera", "no_video", "intervene", "out", "run_name"} <= set(FILE_KEYS)
    outside = sorted(o.flag for cls, _ in RUN_OPTIONS for _, o in options(cls) if not o.hashed)
    # the manifest's statistics, presentation (the colour map), recovery and pre-flight check, the folder's path; the
    # space check changes no file; a served policy's conventions file enters the model fingerprint by its content
    assert outside == ["--ci-method", "--colormap", "--no-space-check", "--out", "--preflight", "--retries", "--run-name",
                       "--served-conventions"]


def test_robustness_takes_runs_options_and_states_only_where_it_differs():
    from harness.cli.robustness import DIFFERS

    run, rob = _flags(_subparser("run")), _flags(_subparser("robustness"))
    shared = sorted(set(run) & set(rob) - {"--out", "--protocol", "--overwrite", "--workers", "--executor",
                                           "--ray-address", "--policy-replicas"})
    assert shared == ["--action-consistency", "--action-samples", "--attention-controls", "--controls-every", "--episodes",
                      "--fast-render", "--max-steps", "--model", "--no-video", "--perturb", "--png-every",
                      "--readout-features-every", "--reliance-every", "--reliance-fill", "--seed",
                      "--served-conventions", "--task", "--text-tokenizer"]
    for flag in shared:
        a, b = run[flag], rob[flag]
        assert (a.dest, a.type, a.choices, a.nargs, type(a)) == (b.dest, b.type, b.choices, b.nargs, type(b)), flag
        stated = DIFFERS.get(a.dest, {})
        assert b.default == stated.get("default", a.default) and b.required == stated.get("required", False), flag
    assert rob["--episodes"].default == 20 and rob["--png-every"].default == 0 and run["--episodes"].default is None


def _declarations(flag: str) -> list[str]:
    """The modules of harness/ and envs/ whose calls take `flag` as an argument (add_argument, option, dict)."""
    found = []
    for path in [*HARNESS.rglob("*.py"), *(HARNESS.parent / "envs").rglob("*.py")]:
        text = path.read_text()
        for node in ast.walk(ast.parse(text)) if f'"{flag}"' in text else ():
            if isinstance(node, ast.Call) and any(isinstance(a, ast.Constant) and a.value == flag
                                                  for a in [*node.args, *(k.value for k in node.keywords)]):
                found.append(path.name)
    return found


def test_the_shared_flags_are_declared_once():
    for flag in ("--verbose", "--alpha", "--max-drop", "--fail-on", "--png-every", "--ci-method", "--faithfulness-fill",
                 "--fast-render"):
        assert len(_declarations(flag)) == 1, (flag, _declarations(flag))
    assert _declarations("--out") != [] and len(_declarations("--out")) > 1  # the check sees several
    compare, regress = _flags(_subparser("compare")), _flags(_subparser("regress"))
    assert compare["--fail-on"].choices == regress["--fail-on"].choices and compare["--alpha"].default == 0.05
    assert compare["--alpha"].help != regress["--alpha"].help  # each command's own wording, from the one field


def test_adding_an_option_is_one_field():
    """A dataclass with one new field: its flag, its protocol-file key, its value from settings, its record (only when
    set, as a sparse option) and its docs row all follow, with no other line written."""

    @dataclass(frozen=True)
    class Options:
        png_every: int = option(1, "--png-every", "write overlays every n-th step", type=int, file=(int,))
        margin: float = option(0.15, "--margin", "the largest drop that still HOLDS", type=float,
                               file=(int, float), sparse=True)

    parser = argparse.ArgumentParser()
    add_arguments(parser, [Options])
    args = parser.parse_args(["--margin", "0.2"])
    assert args.margin == 0.2 and args.png_every is None  # not given: None, the next source decides
    assert file_keys(Options) == {"png_every": (int,), "margin": (int, float)}
    assert Options(**given(Options, vars(args))) == Options(margin=0.2)
    assert record(Options()) == {"png_every": 1} and record(Options(margin=0.2)) == {"png_every": 1, "margin": 0.2}
    assert "| `--margin MARGIN` | the largest drop that still HOLDS [0.15] | `protocol.margin` (when set) |" in \
        table([(Options, "protocol")])


def test_the_records_of_the_options_are_those_the_protocols_were_hashed_with():
    """The sparse options are left out at their default: protocols made before them keep their hash."""
    from harness.outputs.writers import OutputOptions
    from harness.policy import PolicyConfig
    from harness.run.protocol import Protocol

    assert set(PolicyConfig().to_dict()) == {f.name for f in dataclasses.fields(PolicyConfig)} - {
        "intervention", "attribution", "faithfulness_every", "faithfulness_fill", "attention_controls", "controls_every", "reliance_every", "reliance_fill",
        "readout_features_every", "action_consistency", "action_samples"}
    assert "overlay_interpolation" not in OutputOptions().to_dict() and "rerun" not in OutputOptions().to_dict()
    assert OutputOptions(rerun=True).to_dict()["rerun"] is True
    plain = Protocol(model="random:octo-small-1.5", tasks=("Lift",)).to_dict()
    assert "perturb" not in plain and "text_tokenizer" not in plain
    chosen = Protocol(model="random:octo-small-1.5", tasks=("Lift",), perturb="lighting:2", text_tokenizer="fallback")
    assert list(chosen.to_dict())[-2:] == ["text_tokenizer", "perturb"]

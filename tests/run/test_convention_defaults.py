"""Conventions resolve command line > the checkpoint's harness.toml > the task family's default (issue 43 item 1):
LIBERO's default is the published protocol (rot180 images, libero actions), robosuite's is as before; a run mixing
families gives each its own; the manifest records each convention's source and the console names a default used."""

from __future__ import annotations

import json
import logging

import pytest

from harness.run.protocol import Protocol
from harness.run.settings import build_protocol

REFERENCE_LIBERO = "models/octo-reference-libero-object"  # its harness.toml: rot180, libero, 128/128 cameras


def _pair(options):
    return options.image_convention, options.action_space


def test_libero_without_harness_toml_takes_the_published_protocol_and_robosuite_stays_as_before():
    libero = build_protocol({"task": ["libero_object"], "model": "random:octo-small-1.5"})
    assert _pair(libero.env) == ("rot180", "libero") and libero.family_env is None  # one family: folded into env
    assert libero.convention_sources == {"libero": {k: "default:libero" for k in
                                                    ("cameras", "image_convention", "action_space")}}
    lift = build_protocol({"task": ["Lift"], "model": "random:octo-small-1.5"})
    assert _pair(lift.env) == ("upright", "octo-delta") and lift.family_env is None
    assert "family_env" not in lift.to_dict()  # robosuite protocols keep their hash
    assert lift.convention_sources["robosuite"]["action_space"] == "default:robosuite"


def test_flag_beats_checkpoint_beats_family_default(tmp_path):
    flag = build_protocol({"task": ["libero_object/1"], "model": "random:octo-small-1.5", "action_space": "robosuite"})
    assert _pair(flag.env) == ("rot180", "robosuite")
    assert flag.convention_sources["libero"]["action_space"] == "flag"
    assert flag.convention_sources["libero"]["image_convention"] == "default:libero"
    (tmp_path / "harness.toml").write_text('format = "octo-harness-conventions/1"\n[env]\nimage_convention = "opengl"\n')
    mine = build_protocol({"task": ["libero_object/1"], "model": f"random:{tmp_path}"})
    assert _pair(mine.env) == ("opengl", "libero")
    assert mine.convention_sources["libero"]["image_convention"] == "checkpoint"
    both = build_protocol({"task": ["libero_object/1"], "model": f"random:{tmp_path}", "image_convention": "upright"})
    assert both.env.image_convention == "upright" and both.convention_sources["libero"]["image_convention"] == "flag"


def test_a_mixed_run_applies_each_familys_default_to_its_own_tasks_and_round_trips():
    mixed = build_protocol({"task": ["Lift", "libero_object/2"], "model": "random:octo-small-1.5",
                            "hold_gripper": "open"})
    assert _pair(mixed.env_for("Lift")) == ("upright", "octo-delta")
    assert _pair(mixed.env_for("libero_object/2")) == ("rot180", "libero")
    assert mixed.env_for("Lift").hold_gripper == 1.0 and mixed.env_for("libero_object/2").hold_gripper == 1.0
    back = Protocol.from_dict(json.loads(json.dumps(mixed.to_dict())))
    assert back.to_dict() == mixed.to_dict() and _pair(back.env_for("libero_object/2")) == ("rot180", "libero")
    flagged = build_protocol({"task": ["Lift", "libero_object/2"], "model": "random:octo-small-1.5",
                              "image_convention": "upright", "action_space": "octo-delta"})
    assert flagged.family_env is None  # the flags decide for both families


def test_console_line_names_the_default_only_where_one_is_used():
    from harness.run.driver import _default_lines

    lines = _default_lines(build_protocol({"task": ["libero_object/0", "libero_object/3"],
                                           "model": "random:octo-small-1.5"}))
    assert lines == ["libero_object: rot180 images, libero actions "
                     "(published protocol; random:octo-small-1.5 has no harness.toml)"]
    assert _default_lines(build_protocol({"task": ["libero_object/0"], "model": REFERENCE_LIBERO})) == []


@pytest.mark.slow
def test_manifest_records_sources_and_the_run_logs_the_default(fixtures_dir, tmp_path, caplog):
    from harness.run.driver import execute

    protocol = build_protocol({"task": ["Lift"], "model": str(fixtures_dir / "tiny"), "max_steps": 2,
                               "png_every": 0, "no_video": True, "fast_render": True})
    with caplog.at_level(logging.INFO, logger="harness"):
        summary = execute(protocol, tmp_path / "runs", "defaults", progress=False)
    manifest = json.loads((summary.run_dir / "manifest.json").read_text())
    assert manifest["conventions"] == {"robosuite": {"cameras": "default:robosuite", "image_convention":
                                                     "default:robosuite", "action_space": "default:robosuite"}}
    assert [r.getMessage() for r in caplog.records if "octo-delta actions" in r.getMessage()] == [
        "Lift: upright images, octo-delta actions (the harness's robosuite default; tiny has no harness.toml)"]

"""Pre-flight known answers on real renders (issue 65): each reference checkpoint is consistent with its own
conventions on a task and state its example frame did not come from; vertical differences are MISMATCH naming the
flag that fits; mirror-only differences are what the measured margins allow; blank and synthetic example frames are
inconclusive; a wrong action space is MISMATCH. One env reset per family, shared by every test here."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from envs.options import to_convention
from harness.octo import checkpoint
from harness.run.preflight import (CONSISTENT, INCONCLUSIVE, MISMATCH, PreflightMismatch, action_finding,
                                   example_frames, first_frames, image_finding, record, report, summary)

REPO = Path(__file__).resolve().parents[2]
MODELS = REPO / "models"
ROBOSUITE = ("octo-reference-robosuite", "octo-reference-robosuite-64px")
LIBERO = ("octo-reference-libero-object", "octo-reference-libero-object-first")
TRAINED = {**{m: "upright" for m in ROBOSUITE}, **{m: "rot180" for m in LIBERO}}
SPACE = {**{m: "robosuite" for m in ROBOSUITE}, **{m: "libero" for m in LIBERO}}


def _checkpoint(folder: Path) -> SimpleNamespace:
    """What the check reads of a model: its example batch and statistics (no parameters loaded)."""
    return SimpleNamespace(example_batch=checkpoint.read_example_batch(folder),
                           dataset_statistics=json.loads((folder / "dataset_statistics.json").read_text()))


def _upright_frames(model: str, task: str) -> dict[str, np.ndarray]:
    """The first frame (seed 0) of each camera, rendered as a run of `model` on `task` feeds it, turned upright."""
    import envs
    from harness.run.settings import build_protocol

    protocol = build_protocol({"model": str(MODELS / model), "task": [task]})
    options = protocol.env_for(protocol.tasks[0])
    env = envs.make(protocol.tasks[0], options)
    try:
        return {k: to_convention(v, options.image_convention) for k, v in first_frames(env, 0).items()}
    finally:
        env.close()


@pytest.fixture(scope="module")
def robosuite_frames():
    return _upright_frames("octo-reference-robosuite", "Lift")  # the example frames: Stack (seed 200000)


@pytest.fixture(scope="module")
def libero_frames():
    from tests.helpers import needs_libero

    needs_libero()
    return _upright_frames("octo-reference-libero-object", "libero_object/0")  # the example frames: /5


def _verdicts(model: str, upright: dict, fed: str) -> dict[str, dict]:
    examples = example_frames(_checkpoint(MODELS / model))
    default = "upright" if model in ROBOSUITE else "rot180"  # the family's own (harness.conventions.FAMILY_DEFAULTS)
    return {k: image_finding(k, examples[k], to_convention(upright[k], fed), fed, default) for k in examples}


def _frames(model, robosuite_frames, libero_frames):
    return robosuite_frames if model in ROBOSUITE else libero_frames


@pytest.mark.slow
@pytest.mark.parametrize("model", ROBOSUITE + LIBERO)
def test_each_reference_checkpoint_is_consistent_with_its_own_conventions(model, request):
    upright = request.getfixturevalue("robosuite_frames" if model in ROBOSUITE else "libero_frames")
    found = _verdicts(model, upright, TRAINED[model])
    assert {k: f["verdict"] for k, f in found.items()} == {k: CONSISTENT for k in found}
    assert report("strict", list(found.values())) == []  # nothing said, nothing refused


@pytest.mark.slow
@pytest.mark.parametrize("model", ROBOSUITE + LIBERO)
def test_a_vertical_difference_is_a_mismatch_naming_the_trained_convention(model, request):
    upright = request.getfixturevalue("robosuite_frames" if model in ROBOSUITE else "libero_frames")
    for k, f in _verdicts(model, upright, "opengl").items():
        assert f["verdict"] == MISMATCH and TRAINED[model] in f["suggest"], f
        assert f"--image-convention {TRAINED[model]}" in f["line"] and f["line"].startswith(f"{k}: MISMATCH")


@pytest.mark.slow
def test_a_mirror_only_difference_is_what_the_margins_allow(robosuite_frames, libero_frames):
    """Mirror margins (model cards): robosuite's views -0.01 to 0.01 and LIBERO-Object's wrist view -0.05 to 0.07,
    under MIRROR_MARGIN 0.1: inconclusive; LIBERO-Object's agentview 0.13 to 0.20: MISMATCH naming rot180."""
    for k, f in _verdicts("octo-reference-robosuite", robosuite_frames, "rot180").items():
        assert f["verdict"] == INCONCLUSIVE and "mirror-only difference not measurable" in f["line"], f
    libero = _verdicts("octo-reference-libero-object", libero_frames, "upright")
    assert libero["image_primary"]["verdict"] == MISMATCH and libero["image_primary"]["suggest"] == ["rot180"]
    assert "--image-convention rot180" in libero["image_primary"]["line"]
    assert libero["image_wrist"]["verdict"] == INCONCLUSIVE and libero["image_wrist"]["reason"] == "mirror-only difference"


@pytest.mark.slow
def test_upside_down_example_frames_are_told_to_use_opengl(robosuite_frames):
    """A checkpoint trained on frames stored as robosuite renders them (a robomimic finetune), run as upright."""
    examples = example_frames(_checkpoint(MODELS / "octo-reference-robosuite"))
    for key, example in examples.items():
        f = image_finding(key, example[::-1], robosuite_frames[key], "upright", "upright")
        assert f["verdict"] == MISMATCH and f["suggest"] == ["opengl"], f
        assert "--image-convention opengl" in f["line"]


@pytest.mark.slow
def test_blank_and_synthetic_example_frames_are_inconclusive(fixtures_dir, robosuite_frames):
    from harness.octo import presets
    from harness.octo.config import OctoConfig
    from harness.octo.loading import _synthetic_example_batch

    tiny = example_frames(_checkpoint(fixtures_dir / "tiny"))
    # the example batch `load_pretrained("random:octo-small-1.5")` makes for the released configuration (the check
    # reads no weights, so none are drawn here)
    config = OctoConfig.from_json(fixtures_dir / "released" / "octo-small-1.5.config.json")
    batch = _synthetic_example_batch(config, presets.IMAGE_SIZES, presets.WINDOW_SIZE)
    octo_small = example_frames(SimpleNamespace(example_batch=batch))
    assert tiny and octo_small
    for key, example in [*tiny.items(), *octo_small.items()]:
        f = image_finding(key, example, robosuite_frames.get(key, robosuite_frames["image_primary"]), "upright", "upright")
        assert f["verdict"] == INCONCLUSIVE and f["reason"] == "blank example frame"


@pytest.mark.slow
def test_a_multi_dataset_checkpoints_example_frame_is_inconclusive(robosuite_frames):
    """A pretrained mixture's example frame shows one of its datasets: even a vertical mistake is not claimed."""
    example = example_frames(_checkpoint(MODELS / "octo-reference-robosuite"))["image_primary"]
    f = image_finding("image_primary", example, robosuite_frames["image_primary"][::-1], "opengl", "upright", 25)
    assert f["verdict"] == INCONCLUSIVE and f["reason"] == "multi-dataset checkpoint"


@pytest.mark.slow
def test_another_scene_fed_the_right_way_up_is_never_a_mismatch(robosuite_frames):
    """The LIBERO checkpoint's example frames against a robosuite render fed upright or rot180 (both the right way
    up for it): another table, another robot pose, and no MISMATCH."""
    examples = example_frames(_checkpoint(MODELS / "octo-reference-libero-object"))
    for fed in ("upright", "rot180"):
        for key, example in examples.items():
            f = image_finding(key, example, to_convention(robosuite_frames[key], fed), fed, "upright")
            assert f["verdict"] != MISMATCH, f


@pytest.mark.parametrize("model", ROBOSUITE + LIBERO)
def test_a_wrong_action_space_is_a_mismatch_and_the_right_one_consistent(model):
    statistics = _checkpoint(MODELS / model).dataset_statistics
    (key,) = statistics
    assert action_finding(statistics, key, SPACE[model])["verdict"] == CONSISTENT
    for wrong in {"octo-delta", "robosuite", "libero"} - {SPACE[model]}:
        f = action_finding(statistics, key, wrong)
        assert f["verdict"] == MISMATCH and f["suggest"] == [SPACE[model]], f
        assert f"--action-space {SPACE[model]}" in f["line"]


def test_bridge_like_statistics_fit_octo_delta_and_one_ended_grippers_are_not_guessed():
    bridge = {"b": {"action": {"p01": [-0.03, -0.03, -0.02, -0.1, -0.1, -0.1, 0.0],
                               "p99": [0.03, 0.03, 0.02, 0.1, 0.1, 0.1, 1.0],
                               "min": [-0.1] * 6 + [0.0], "max": [0.1] * 6 + [1.0]}}}
    assert action_finding(bridge, "b", "octo-delta")["verdict"] == CONSISTENT
    assert action_finding(bridge, "b", "libero")["suggest"] == ["octo-delta"]
    held = {"b": {"action": {**bridge["b"]["action"], "min": [-0.1] * 6 + [1.0]}}}  # gripper never closes
    f = action_finding(held, "b", "octo-delta")
    assert f["verdict"] == INCONCLUSIVE and "gripper" in f["reason"]
    assert action_finding(None, "b", "octo-delta")["verdict"] == INCONCLUSIVE


@pytest.mark.slow
def test_strict_refuses_a_mismatch_and_warn_says_one_line_per_finding(robosuite_frames):
    examples = example_frames(_checkpoint(MODELS / "octo-reference-robosuite"))
    found = [image_finding(k, e, to_convention(robosuite_frames[k], "opengl"), "opengl", "upright")
             for k, e in examples.items()]
    assert len(report("warn", found)) == len(found)
    with pytest.raises(PreflightMismatch, match="--image-convention upright"):
        report("strict", found)


@pytest.mark.slow
def test_the_manifest_block_and_the_report_line(robosuite_frames):
    examples = example_frames(_checkpoint(MODELS / "octo-reference-robosuite"))
    found = [image_finding(k, e, to_convention(robosuite_frames[k], "opengl"), "opengl", "upright")
             for k, e in examples.items()]
    block = record("warn", found, "Lift")
    assert block["task"] == "Lift" and all("line" not in f for f in block["findings"])
    assert summary(block) == ("warn: image:image_primary: MISMATCH (fits upright or rot180); "
                              "image:image_wrist: MISMATCH (fits upright or rot180)")  # robosuite: mirrors tie
    assert summary({"mode": "off"}) == "off" and summary(None).startswith("not run")


@pytest.mark.slow
def test_the_verdicts_do_not_read_harness_toml(tmp_path, robosuite_frames):
    """A copy of the checkpoint without its conventions file gives the same verdicts for the same fed frames."""
    copy = tmp_path / "ckpt"
    shutil.copytree(MODELS / "octo-reference-robosuite", copy, ignore=shutil.ignore_patterns("harness.toml", "6000"))
    for fed in ("upright", "opengl"):
        a = _verdicts("octo-reference-robosuite", robosuite_frames, fed)
        examples = example_frames(_checkpoint(copy))
        b = {k: image_finding(k, examples[k], to_convention(robosuite_frames[k], fed), fed, "upright") for k in examples}
        assert a == b


def test_a_protocol_file_sets_the_mode_and_a_wrong_one_is_one_line(tmp_path):
    from harness.run.preflight import PreflightOptions
    from harness.run.settings import read_protocol_file

    (tmp_path / "eval.toml").write_text('task = "Lift"\npreflight = "strict"\n')
    assert PreflightOptions(read_protocol_file(tmp_path / "eval.toml")["preflight"]).mode == "strict"
    with pytest.raises(ValueError, match="--preflight 'loud': use one of warn, strict, off"):
        PreflightOptions("loud")


@pytest.mark.slow
def test_strict_run_exits_2_before_the_first_episode(tmp_path, capsys):
    """As a user would (the command line, in this process): a vertical mistake with --preflight strict is one error
    line and exit 2, and no run folder is left."""
    from harness.cli import main

    code = main(["run", "--model", str(MODELS / "octo-reference-robosuite"), "--task", "Lift", "--image-convention",
                 "opengl", "--preflight", "strict", "--out", str(tmp_path), "--run-name", "r"])
    err = capsys.readouterr().err
    assert code == 2, err[-2000:]
    assert "MISMATCH" in err and "--image-convention upright" in err and len(err.strip().splitlines()[-1]) > 0
    assert not (tmp_path / "r").exists()

"""6-D (arm-only) models on robosuite: --hold-gripper holds the gripper at a stated value (recorded), else a refusal
that names the option."""

import json

import numpy as np
import pytest

import envs
from envs.options import EnvConfigError, EnvOptions
from harness import cli
from harness.run.settings import build_protocol


def test_open_and_closed_are_the_action_space_values_and_recorded_only_when_set():
    assert EnvOptions(hold_gripper="open").hold_gripper == 1.0
    assert EnvOptions(hold_gripper="closed").hold_gripper == 0.0
    assert EnvOptions(hold_gripper="open", action_space="robosuite").hold_gripper == -1.0
    assert EnvOptions(hold_gripper="0.25").hold_gripper == 0.25
    for bad in (1.5, "half", True):
        with pytest.raises(EnvConfigError, match="--hold-gripper"):
            EnvOptions(hold_gripper=bad)
    assert "hold_gripper" not in EnvOptions().to_dict()  # protocols without it keep their hash
    held = EnvOptions(hold_gripper="closed", action_space="robosuite")
    assert EnvOptions.from_dict(held.to_dict()) == held and held.to_dict()["hold_gripper"] == 1.0
    protocol = build_protocol({"task": ["Lift"], "model": "random:octo-small-1.5", "hold_gripper": "open"})
    assert protocol.to_dict()["env"]["hold_gripper"] == 1.0


def test_env_takes_six_values_and_holds_the_gripper():
    held = envs.make("Lift", EnvOptions(hold_gripper="closed", cameras=()))
    full = envs.make("Lift", EnvOptions(cameras=()))
    try:
        assert held.action_space.shape == (6,) and full.action_space.shape == (7,)
        a, _ = held.reset(seed=3)
        b, _ = full.reset(seed=3)
        arm = np.array([0.01, 0.0, -0.01, 0.0, 0.0, 0.02], np.float32)
        for _ in range(4):
            a, *_ = held.step(arm)
            b, *_ = full.step(np.append(arm, 0.0))  # octo-delta: 0 = closed
        np.testing.assert_array_equal(a["proprio"], b["proprio"])  # the same commands reached the robot
        with pytest.raises(ValueError, match="takes 6-D actions"):
            held.step(np.zeros(7, np.float32))
    finally:
        held.close()
        full.close()


@pytest.mark.slow
def test_six_d_model_is_refused_naming_the_option_then_runs_with_it(fixtures_dir, tmp_path, capsys):
    from tests.policy.test_finetuned_checkpoints import build_finetune_checkpoint

    six = build_finetune_checkpoint(tmp_path / "six", fixtures_dir, action_dim=6, save=False)
    args = ["run", "--task", "Lift", "--model", f"random:{six}", "--max-steps", "2", "--png-every", "0", "--no-video",
            "--fast-render", "--out", str(tmp_path / "runs")]
    assert cli.main([*args, "--run-name", "refused"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "6-D" in err[0] and "--hold-gripper open|closed|VALUE" in err[0]
    assert cli.main([*args, "--run-name", "held", "--hold-gripper", "open"]) == 0
    run = tmp_path / "runs" / "held"
    assert json.loads((run / "manifest.json").read_text())["protocol"]["env"]["hold_gripper"] == 1.0
    with np.load(run / "Lift" / "episode_0" / "actions.npz") as z:
        assert z["executed"].shape[-1] == 6
    # a 7-D model with --hold-gripper: refused, naming what to drop
    assert cli.main(["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--max-steps", "1",
                     "--hold-gripper", "open", "--out", str(tmp_path / "runs"), "--run-name", "seven"]) == 2
    assert "drop --hold-gripper" in capsys.readouterr().err

"""DAgger round of the reference pipeline: the state-based PickPlaceCan expert in the real simulator (it
finishes the task from states it did not lead to), correction collection with the committed policy acting,
merging corrections into the demonstrations, and normalisation that keeps the demonstrations' units."""

import json
import logging
from pathlib import Path

import numpy as np
import pytest

import envs
from reference_policies import dagger
from reference_policies.demos import TRAIN_SEED_BASE, EVAL_SEEDS
from reference_policies.experts import CLOSED, OPEN, CanLabeller, ExpertConfig
from reference_policies.pipeline import main as pipeline_main
from reference_policies.train import DATASET_KEY, build_dataset

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "models" / "octo-reference-robosuite"


def _labeller_episode(seed: int, push_steps: range = range(0), noise: float = 0.3) -> tuple[bool, list[float]]:
    """Drive PickPlaceCan with CanLabeller's actions (plus DART noise); during `push_steps` the arm is pushed
    towards the far corner instead, off any path the phase-machine expert takes. (success, gripper labels)."""
    env = envs.make("PickPlaceCan", cameras={}, action_space="robosuite", max_episode_steps=300)
    try:
        rng = np.random.default_rng(seed)
        obs, info = env.reset(seed=seed)
        labeller = CanLabeller()
        labeller.reset(obs, env)
        grippers = []
        for t in range(300):
            action = labeller.act(obs, env)
            grippers.append(float(action[6]))
            if t in push_steps:
                action[:3] = (1.0, 1.0, 0.0)
            action[:3] = np.clip(action[:3] + noise * rng.standard_normal(3), -1.0, 1.0)
            obs, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                break
        return bool(info["success"]), grippers
    finally:
        env.close()


@pytest.mark.slow
def test_state_expert_places_the_can_under_noise():
    success, grippers = _labeller_episode(seed=0)
    assert success
    # open to approach, closed to carry, open again to release: the phases are read off the state
    changes = [g for i, g in enumerate(grippers) if i == 0 or g != grippers[i - 1]]
    assert changes[:3] == [OPEN, CLOSED, OPEN]


@pytest.mark.slow
def test_state_expert_recovers_after_the_arm_is_pushed_away():
    # a push can tip the can over (then no expert recovers): 3 of 4 seeds succeed here, demand 2 of 3
    successes = [_labeller_episode(seed=seed, push_steps=range(30, 50))[0] for seed in (1, 3, 7)]
    assert sum(successes) >= 2, successes


def test_state_expert_needs_reset():
    env = envs.make("PickPlaceCan", cameras={}, action_space="robosuite")
    try:
        obs, _ = env.reset(seed=0)
        with pytest.raises(RuntimeError, match="reset"):
            CanLabeller().act(obs, env)
    finally:
        env.close()


def test_grasp_and_placement_queries_name_unknown_objects():
    env = envs.make("PickPlaceCan", cameras={}, action_space="robosuite")
    try:
        env.reset(seed=0)
        assert env.grasping("Can") is False
        assert env.over_placement("Can") is False  # the can starts on the other table
        with pytest.raises(KeyError, match="objects: .*Can"):
            env.grasping("Door")
    finally:
        env.close()


def test_dagger_seeds_are_disjoint_from_demonstrations_and_evaluation():
    assert dagger.DAGGER_SEED_BASE >= EVAL_SEEDS
    assert dagger.DAGGER_SEED_BASE >= TRAIN_SEED_BASE + 100_000 * 3  # after the three tasks' demonstration blocks
    with pytest.raises(ValueError, match="no state-based expert"):
        dagger.DaggerConfig(task="Lift")
    with pytest.raises(ValueError, match="--episodes"):
        dagger.DaggerConfig(episodes=2)


@pytest.mark.slow
def test_collection_labels_the_policys_own_states(tmp_path, caplog):
    """4 episodes (one per collection job, the fewest the split allows) of 6 steps (was 12): the checks are about
    episode boundaries, the first frame, labels of the approach phase (the gripper label stays open through the
    first 12 steps, so through 6) and which jobs run again, none needs more; each step is a 128-px inference."""
    config = dagger.DaggerConfig(episodes=4, max_steps=6)
    summary = dagger.collect(MODEL, tmp_path / "c", config, workers=1)
    with np.load(tmp_path / "c" / "PickPlaceCan.npz") as data:
        arrays = {k: data[k] for k in data.files}
    assert summary["PickPlaceCan"]["steps"] == 24 and summary["PickPlaceCan"]["policy_successes"] == 0
    assert list(arrays["seeds"]) == [dagger.DAGGER_SEED_BASE + k for k in range(4)]
    assert arrays["image_primary"].shape == (24, 128, 128, 3) and arrays["image_wrist"].shape == (24, 64, 64, 3)
    assert list(arrays["lengths"]) == [6] * 4 and list(arrays["step"][:7]) == [*range(6), 0]
    # labels are the expert's: arm inputs in [-1, 1], the gripper open while it approaches the can
    assert np.all(np.abs(arrays["action"][:, :6]) <= 1.0) and np.all(arrays["action"][:, 6] == OPEN)
    # the states are the policy's: its first frame is the env's reset frame, resized as the policy resizes it
    env = envs.make("PickPlaceCan", fast_render=True, action_space="robosuite")
    try:
        from harness.policy import resize_frame

        obs, _ = env.reset(seed=dagger.DAGGER_SEED_BASE)
        np.testing.assert_array_equal(arrays["image_primary"][0], resize_frame(obs["image_primary"], (128, 128)))
        np.testing.assert_array_equal(arrays["proprio"][0], obs["proprio"])
    finally:
        env.close()
    # the same collection with the same checkpoint is found again; another checkpoint's is not
    assert dagger.existing(config, MODEL, tmp_path / "c") == json.loads((tmp_path / "c" / "summary.json").read_text())
    other = ROOT / "models" / "octo-reference-robosuite-64px"
    assert dagger.existing(config, other, tmp_path / "c") is None
    assert dagger.existing(dagger.DaggerConfig(episodes=8, max_steps=6), MODEL, tmp_path / "c") is None
    relabelled = dagger.DaggerConfig(episodes=4, max_steps=6, expert=ExpertConfig(bin_inset=(0.0, 0.04)))
    assert dagger.existing(relabelled, MODEL, tmp_path / "c") is None  # labels from another carry point
    # a stop after three jobs: only the fourth runs again (a torn file counts as missing), same arrays
    whole = arrays
    for name in ("PickPlaceCan.npz", "summary.json", f"jobs/PickPlaceCan_{dagger.DAGGER_SEED_BASE + 3}.npz"):
        (tmp_path / "c" / name).unlink()
    (tmp_path / "c" / "jobs" / f"PickPlaceCan_{dagger.DAGGER_SEED_BASE + 2}.npz").write_bytes(b"torn")
    with caplog.at_level(logging.INFO, logger="reference_policies.demos"):
        dagger.collect(MODEL, tmp_path / "c", config, workers=1)
    assert "reusing 2 of 4 jobs" in caplog.text
    with np.load(tmp_path / "c" / "PickPlaceCan.npz") as data:
        assert sorted(data.files) == sorted(whole) and all(np.array_equal(data[k], whole[k]) for k in whole)


def _toy(n_episodes: int, length: int, offset: float) -> dict:
    n = n_episodes * length
    return {
        "image_primary": np.zeros((n, 4, 4, 3), np.uint8),
        "proprio": np.full((n, 8), offset, np.float32) + np.arange(n, dtype=np.float32)[:, None],
        "action": np.full((n, 7), offset, np.float32) + np.arange(n, dtype=np.float32)[:, None],
        "episode": np.repeat(np.arange(n_episodes, dtype=np.int32), length),
        "step": np.tile(np.arange(length, dtype=np.int32), n_episodes),
        "seeds": np.arange(n_episodes, dtype=np.int64),
        "lengths": np.full(n_episodes, length, np.int32),
    }


def test_corrections_append_as_new_episodes(tmp_path):
    demos = {"Lift": _toy(1, 3, 0.0), "PickPlaceCan": _toy(2, 3, 0.0)}
    extra = _toy(2, 2, 100.0)
    extra["success"] = np.array([True, False])
    np.savez(tmp_path / "PickPlaceCan.npz", **extra)
    merged = dagger.append_corrections(demos, tmp_path, "PickPlaceCan")
    assert merged["Lift"] is demos["Lift"]
    assert list(merged["PickPlaceCan"]["episode"]) == [0, 0, 0, 1, 1, 1, 2, 2, 3, 3]
    assert list(merged["PickPlaceCan"]["lengths"]) == [3, 3, 2, 2]
    assert merged["PickPlaceCan"]["action"][6, 0] == 100.0
    del extra["proprio"]
    np.savez(tmp_path / "PickPlaceCan.npz", **extra)
    with pytest.raises(ValueError, match="lacks 'proprio'"):
        dagger.append_corrections(demos, tmp_path, "PickPlaceCan")


def test_normalisation_can_keep_the_demonstrations_statistics():
    demos = {"PickPlaceCan": _toy(2, 3, 0.0)}
    more = {"PickPlaceCan": {k: np.concatenate([v, w]) for (k, v), w in
                             zip(demos["PickPlaceCan"].items(), _toy(2, 3, 50.0).values())}}
    more["PickPlaceCan"]["episode"][6:] += 2
    kept = build_dataset(more, 2, normalise_with=demos)
    own = build_dataset(more, 2)
    stats = kept.statistics[DATASET_KEY]
    np.testing.assert_allclose(stats["action"]["mean"][:6], 2.5)  # mean of 0..5, the demonstrations only
    np.testing.assert_allclose(stats["proprio"]["std"], np.std(np.arange(6.0)), rtol=1e-6)
    assert own.statistics[DATASET_KEY]["action"]["mean"][0] > 20  # the default uses everything
    assert stats["num_transitions"] == 12  # counts still describe the training data
    np.testing.assert_allclose(kept.actions[0, 0, 0], (0 - 2.5) / np.std(np.arange(6.0)), rtol=1e-6)


def test_pipeline_rejects_a_dagger_round_too_small_to_split(capsys):
    with pytest.raises(SystemExit) as exit_info:
        pipeline_main(["--dagger-episodes", "2", "--out", "/nonexistent/x"])
    assert exit_info.value.code == 2
    assert "--dagger-episodes must be 0 (no DAgger round) or >= 4 (one per collection job)" in capsys.readouterr().err


@pytest.mark.parametrize("weights", ["libero_object/0", "libero_object/0=0", "libero_object/0=-1", "Lift=2",
                                     "libero_object/0=inf", "libero_object/0=x", "libero_object/0=2,libero_object/0=3"])
def test_pipeline_refuses_task_weights_it_cannot_use_in_one_line_before_loading_anything(weights, capsys):
    from reference_policies.libero_pipeline import main as libero_pipeline_main

    with pytest.raises(SystemExit) as exit_info:
        libero_pipeline_main(["--task-weights", weights, "--out", "/nonexistent/x", "--data", "/nonexistent/d"])
    assert exit_info.value.code == 2
    (line,) = [text for text in capsys.readouterr().err.splitlines() if "error:" in text]
    assert ("is not TASK=W with TASK one of libero_object/0 .. libero_object/9" in line
            or "--task-weights names a task twice" in line), line


def test_task_weights_name_libero_tasks_and_leave_the_others_at_one():
    from reference_policies.libero_pipeline import RECIPES, parse_task_weights

    tasks = RECIPES["second"].tasks
    assert parse_task_weights("", tasks) == ()
    assert parse_task_weights("libero_object/0=3, libero_object/8=1.5", tasks) == (
        ("libero_object/0", 3.0), ("libero_object/8", 1.5))


def test_dagger_tasks_keep_the_recipes_order_and_unknown_ones_are_refused_in_one_line(capsys):
    from reference_policies.libero_pipeline import RECIPES, main as libero_pipeline_main, parse_tasks

    tasks = RECIPES["second"].tasks
    assert parse_tasks("", tasks) == tasks
    assert parse_tasks("libero_object/8, libero_object/0", tasks) == ("libero_object/0", "libero_object/8")
    with pytest.raises(SystemExit) as exit_info:
        libero_pipeline_main(["--dagger-episodes", "6", "--dagger-tasks", "libero_object/0,libero_goal/1",
                              "--out", "/nonexistent/x", "--data", "/nonexistent/d"])
    assert exit_info.value.code == 2
    (line,) = [text for text in capsys.readouterr().err.splitlines() if "error:" in text]
    assert "--dagger-tasks: 'libero_goal/1' is not a task of the recipe" in line


@pytest.mark.parametrize("option", ["--close-below-top", "--dagger-close-below-top"])
@pytest.mark.parametrize("value", ["-0.001", "0.05", "nan", "inf"])
def test_pipeline_refuses_a_close_below_top_out_of_range_in_one_line(option, value, capsys):
    from reference_policies.libero_pipeline import main as libero_pipeline_main

    with pytest.raises(SystemExit) as exit_info:
        libero_pipeline_main(["--dagger-episodes", "6", f"{option}={value}", "--out", "/nonexistent/x",
                              "--data", "/nonexistent/d"])
    assert exit_info.value.code == 2
    (line,) = [text for text in capsys.readouterr().err.splitlines() if "error:" in text]
    assert f"{option} must be at least 0 and under 0.05 (metres)" in line


@pytest.mark.parametrize("value", ["-1", "1001", "x"])
def test_pipeline_refuses_a_swap_count_out_of_range_in_one_line(value, capsys):
    from reference_policies.libero_pipeline import main as libero_pipeline_main

    with pytest.raises(SystemExit) as exit_info:
        libero_pipeline_main([f"--swaps={value}", "--out", "/nonexistent/x", "--data", "/nonexistent/d"])
    assert exit_info.value.code == 2
    (line,) = [text for text in capsys.readouterr().err.splitlines() if "error:" in text]
    assert "--swaps" in line


@pytest.mark.parametrize("flags,words", [(["--dagger-retrain"], "give it with --dagger-episodes N"),
                                         (["--dagger-episodes", "6", "--dagger-retrain", "--dagger-steps", "100"],
                                          "leave out --dagger-steps"),
                                         (["--dagger-episodes", "6", "--dagger-retrain", "--dagger-learning-rate", "1e-4"],
                                          "leave out --dagger-steps"),
                                         (["--missed-grasps", "0"], "a probability in (0, 1]"),
                                         (["--missed-grasps", "1.2"], "a probability in (0, 1]"),
                                         (["--missed-grasps", "nan"], "a probability in (0, 1]"),
                                         (["--missed-grasps", "0.5", "--recipe", "first"], "has none of"),
                                         (["--missed-grasps", "0.5", "--demonstrator", "timed"], "state-based")])
def test_pipeline_refuses_retrain_beside_fine_tuning_and_a_bad_missed_grasp_rate_in_one_line(flags, words, capsys):
    from reference_policies.libero_pipeline import _checked, command_parser

    with pytest.raises(SystemExit) as exit_info:
        _checked(command_parser(), [*flags, "--out", "/nonexistent/x", "--data", "/nonexistent/d"])
    assert exit_info.value.code == 2
    (line,) = [text for text in capsys.readouterr().err.splitlines() if "error:" in text]
    assert words in line


def test_a_dagger_round_fine_tunes_1500_steps_at_3e_4_unless_told_otherwise():
    from reference_policies.libero_pipeline import _checked, command_parser

    def round_of(*flags):
        args = _checked(command_parser(), ["--dagger-episodes", "6", "--out", "/nonexistent/x", *flags])[0]
        return args.dagger_steps, args.dagger_learning_rate, args.dagger_retrain

    assert round_of() == (1500, 3e-4, False)
    assert round_of("--dagger-steps", "700", "--dagger-learning-rate", "1e-4") == (700, 1e-4, False)
    assert round_of("--dagger-retrain") == (1500, 3e-4, True)  # unused: the round trains with --steps instead


def test_the_dagger_labeller_closes_as_the_demonstrator_unless_told_otherwise():
    from reference_policies.libero_pipeline import _checked, command_parser

    def labeller_limit(*flags):
        _, _, dagger, _ = _checked(command_parser(), ["--dagger-episodes", "6", "--out", "/nonexistent/x", *flags])
        return dagger.expert.close_below_top

    assert labeller_limit() is None
    assert labeller_limit("--close-below-top", "0.004") == 0.004
    assert labeller_limit("--close-below-top", "0.004", "--dagger-close-below-top", "0") == 0.0
    assert labeller_limit("--dagger-close-below-top", "0.002") == 0.002


def test_each_recipe_writes_its_own_committed_folder_unless_told_otherwise():
    """`--recipe first` without --out rebuilds the first policy's folder, never the reference's."""
    from reference_policies.libero_pipeline import _checked, command_parser

    def out(*flags):
        return _checked(command_parser(), list(flags))[0].out

    assert out() == "models/octo-reference-libero-object"
    assert out("--recipe", "first") == "models/octo-reference-libero-object-first"
    assert out("--recipe", "first", "--out", "/elsewhere") == "/elsewhere"
    for folder in (out(), out("--recipe", "first")):
        assert (Path(__file__).parents[2] / folder / "config.json").is_file()


@pytest.mark.parametrize("option,value", [("--close-below-top", "0.004"), ("--demonstrator-radii", "grasp_height=0.004")])
def test_the_state_demonstrators_options_with_the_timed_demonstrator_are_refused_in_one_line(option, value, capsys):
    from reference_policies.libero_pipeline import main as libero_pipeline_main

    with pytest.raises(SystemExit) as exit_info:
        libero_pipeline_main(["--recipe", "first", option, value, "--out", "/nonexistent/x"])
    assert exit_info.value.code == 2
    assert f"{option} is the state-based demonstrator's" in capsys.readouterr().err


def test_the_demonstrators_radii_reach_its_configuration_and_not_the_dagger_labellers():
    """`--demonstrator-radii` sets the recording's expert (so its fingerprint: a new recording), beside
    --close-below-top; the DAgger labeller keeps its own radii, which must accept the policy's imprecise states."""
    from reference_policies.demos import config_fingerprint
    from reference_policies.libero_expert import LiberoExpertConfig
    from reference_policies.libero_pipeline import RECIPES, _checked, command_parser

    args, _, dagger, _ = _checked(command_parser(), ["--demonstrator-radii", "grasp_height=0.004, at_grasp=0.01",
                                              "--close-below-top", "0.003", "--dagger-episodes", "6", "--out", "/x"])
    expert = args.demonstrator_expert
    assert (expert.grasp_height, expert.at_grasp, expert.close_below_top) == (0.004, 0.01, 0.003)
    assert expert.centred == LiberoExpertConfig().centred
    assert (dagger.expert.grasp_height, dagger.expert.at_grasp) == (LiberoExpertConfig().grasp_height, LiberoExpertConfig().at_grasp)
    plain = _checked(command_parser(), ["--out", "/x"])[0].demonstrator_expert
    assert plain == RECIPES["second"].expert  # no option: the committed recording's fingerprint, reused
    from dataclasses import replace

    assert config_fingerprint(replace(RECIPES["second"], expert=expert)) != config_fingerprint(RECIPES["second"])


@pytest.mark.parametrize("text", ["grasp_height", "grasp_height=0", "grasp_height=0.2", "gain=3", "centred=nan",
                                  "at_grasp=0.01,at_grasp=0.02", "close_below_top=0.004"])
def test_bad_radii_are_refused_in_one_line_before_anything_loads(text, capsys):
    from reference_policies.libero_pipeline import main as libero_pipeline_main
    from reference_policies.libero_probe import main as probe_main

    with pytest.raises(SystemExit) as exit_info:
        libero_pipeline_main(["--demonstrator-radii", text, "--out", "/nonexistent/x", "--data", "/nonexistent/d"])
    assert exit_info.value.code == 2
    (line,) = [t for t in capsys.readouterr().err.splitlines() if "error:" in t]
    assert "--demonstrator-radii: " in line and "NAME one of centred, at_grasp, grasp_height" in line
    with pytest.raises(SystemExit) as exit_info:
        probe_main(["--expert", "--expert-radii", text, "--out", "/nonexistent/p.json"])
    assert exit_info.value.code == 2 and "--expert-radii: " in capsys.readouterr().err


def test_expert_radii_need_the_expert_and_are_part_of_the_probe_key(capsys):
    from reference_policies.libero_probe import main as probe_main, probe_key

    with pytest.raises(SystemExit) as exit_info:
        probe_main(["--model", str(Path(__file__).parents[2] / "models" / "octo-reference-robosuite"),
                    "--expert-radii", "grasp_height=0.004"])
    assert exit_info.value.code == 2 and "give it with --expert" in capsys.readouterr().err
    plain = probe_key(None, [0], ("libero_object/0",), 280)
    assert plain["checkpoint"] == "expert"  # as before: older expert results stay reusable
    assert probe_key(None, [0], ("libero_object/0",), 280, "grasp_height=0.004")["checkpoint"] == "expert grasp_height=0.004"
    assert probe_key(None, [0], ("libero_object/0",), 280, "grasp_height=0.012") == plain  # the default, named


def test_a_finished_stage_one_is_reused_only_with_the_same_configuration(tmp_path):
    from dataclasses import asdict, replace

    from reference_policies.pipeline import finished_training
    from reference_policies.train import TrainConfig

    cfg = TrainConfig(steps=5, init_from="parent")
    demos = {"PickPlaceCan": _toy(2, 3, 0.0)}
    folder = tmp_path / "stage1"
    (folder / "5" / "default").mkdir(parents=True)
    summary = {"config": json.loads(json.dumps(asdict(cfg))), "frames": 6, "train_seconds": 1.0}
    (folder / "training_summary.json").write_text(json.dumps(summary))
    assert finished_training(folder, cfg, demos) is None  # no checkpoint of the last step yet
    (folder / "5" / "default" / "checkpoint").write_bytes(b"x")
    assert finished_training(folder, cfg, demos) == summary
    assert finished_training(folder, replace(cfg, learning_rate=1e-3), demos) is None
    assert finished_training(folder, cfg, {"PickPlaceCan": _toy(3, 3, 0.0)}) is None  # other demonstrations
    # a torn, non-UTF-8 or non-object summary (a stop mid-write by an older version, an edit) reads as unfinished
    for hostile in (json.dumps(summary)[:-7].encode(), b"\xff\xfe{}", b"[1, 2]"):
        (folder / "training_summary.json").write_bytes(hostile)
        assert finished_training(folder, cfg, demos) is None


def test_a_recording_summary_keeps_every_float_digit_so_it_is_found_again(tmp_path):
    from harness.files import atomic_write_json
    from reference_policies.demos import finished_recording

    fingerprint = {"radius": 1 / 3, "scale": 2.0000001, "tiny": 1.234567891e-9, "names": ["Lift"]}
    (tmp_path / "Lift.npz").write_bytes(b"x")
    atomic_write_json(tmp_path / "summary.json", {"Lift": {"episodes": 2}, "config": fingerprint}, exact=True)
    assert finished_recording(tmp_path, fingerprint, ("Lift",))["Lift"] == {"episodes": 2}
    # the rounded writer would lose digits and the recording would be made again
    atomic_write_json(tmp_path / "summary.json", {"config": fingerprint})
    assert finished_recording(tmp_path, fingerprint, ("Lift",)) is None
    assert not list(tmp_path.glob("*.tmp*"))


def test_collection_command_names_a_folder_that_is_not_a_checkpoint(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        dagger.main(["--model", str(tmp_path), "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    assert "not a checkpoint folder" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # nothing written before the check

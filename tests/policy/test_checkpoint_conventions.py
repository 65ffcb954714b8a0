"""Finetune conventions on hand-made inputs: proprio normalisation, the robosuite action space, env options,
checkpoint conventions (harness.toml), the image convention on a marked image, token groups."""

import numpy as np
import pytest

import envs
from envs.actions import ActionAdapterError, passthrough_action
from envs.options import EnvConfigError, EnvOptions, parse_camera
from harness.measures import attention as A
from harness.conventions import CheckpointConventions, ConventionsError
from harness.octo.normalization import NormalizationError, normalize
from harness.octo.tokens import build_token_map

# ------------------------------------------------------------------ proprio normalisation (Octo's NormalizeProprio)

STATS = {
    "mean": [0.5, -1.0, 2.0, 0.0],
    "std": [2.0, 0.5, 1.0, 4.0],
    "p01": [-1.0, -2.0, 0.0, -4.0],
    "p99": [1.0, 0.0, 4.0, 4.0],
    "mask": [True, True, True, False],
}


def test_proprio_mean_std_with_mask_equals_hand_computation():
    x = np.array([[1.5, -2.0, 2.5, 7.0], [0.5, -1.0, 2.0, -3.0]], np.float32)  # (window 2, dims 4)
    expected = np.array([[(1.5 - 0.5) / 2.0, (-2.0 + 1.0) / 0.5, 0.5, 7.0],  # last dim masked: left raw
                         [0.0, 0.0, 0.0, -3.0]])
    np.testing.assert_allclose(normalize(x, STATS, "normal"), expected, rtol=1e-6)


def test_proprio_bounds_with_mask_equals_hand_computation():
    x = np.array([0.5, -3.0, 1.0, 9.0], np.float32)
    # 2 (x - p01) / (p99 - p01) - 1, clipped to [-1, 1]; masked dim raw
    expected = [2 * 1.5 / 2.0 - 1, -1.0, 2 * 1.0 / 4.0 - 1, 9.0]
    np.testing.assert_allclose(normalize(x, STATS, "bounds"), expected, rtol=1e-6)
    np.testing.assert_array_equal(normalize(x, STATS, "none"), x)
    no_mask = {k: v for k, v in STATS.items() if k != "mask"}
    assert normalize(x, no_mask, "normal")[3] == pytest.approx(9.0 / 4.0)


def test_proprio_normalisation_errors_are_one_line():
    with pytest.raises(NormalizationError, match="8 dims but its statistics have 4") as e:
        normalize(np.zeros(8), STATS)
    assert "\n" not in str(e.value)
    with pytest.raises(NormalizationError, match="no dataset statistics"):
        normalize(np.zeros(4), None)
    with pytest.raises(NormalizationError, match="p01"):
        normalize(np.zeros(4), {"mean": [0] * 4, "std": [1] * 4}, "bounds")


# ------------------------------------------------------------------ robosuite action space


def test_robosuite_action_passes_through_and_clips_and_counts():
    a = np.array([0.3, -0.2, 1.0, -1.0, 0.05, 0.0, 1.0])
    out, clipped = passthrough_action(a)
    np.testing.assert_array_equal(out, a)  # exactly the controller input, gripper +1 = closed
    assert not clipped
    out, clipped = passthrough_action(np.array([1.5, 0, 0, 0, 0, -2.0, -1.0]))
    np.testing.assert_array_equal(out, [1.0, 0, 0, 0, 0, -1.0, -1.0])
    assert clipped
    with pytest.raises(ActionAdapterError, match=r"\(7,\)"):
        passthrough_action(np.zeros(6))
    with pytest.raises(ActionAdapterError, match="NaN"):
        passthrough_action(np.array([np.nan] * 7))


# ------------------------------------------------------------------ env options


def test_env_options_parse_and_round_trip():
    assert parse_camera("image_primary=agentview:84") == ("image_primary", "agentview", 84)
    for bad in ("image_primary=agentview", "agentview:84", "image_primary=agentview:0", "=a:3"):
        with pytest.raises(EnvConfigError, match="KEY=camera:size"):
            parse_camera(bad)
    options = EnvOptions(cameras={"image_primary": ("agentview", 84)}, image_convention="opengl", action_space="robosuite")
    assert options.cameras == (("image_primary", "agentview", 84),)
    data = options.to_dict()
    assert data["cameras"] == {"image_primary": ["agentview", 84]}
    assert EnvOptions.from_dict(data) == options and hash(EnvOptions.from_dict(data)) == hash(options)
    assert options.replace(action_space=None, masks=True).masks and options.replace(action_space=None).action_space == "robosuite"
    with pytest.raises(EnvConfigError, match="action space 'delta' unknown"):
        EnvOptions(action_space="delta")
    with pytest.raises(EnvConfigError, match="image convention"):
        EnvOptions(image_convention="flipped")
    with pytest.raises(EnvConfigError, match="unknown env option"):
        EnvOptions.from_dict({"camera": {}})
    with pytest.raises(EnvConfigError, match="repeat"):
        EnvOptions(cameras=["image_primary=agentview:84", "image_primary=sideview:84"])


# ------------------------------------------------------------------ checkpoint conventions (harness.toml)


def test_checkpoint_conventions_round_trip_and_precedence(tmp_path):
    conventions = CheckpointConventions(
        env={"action_space": "robosuite", "image_convention": "opengl", "cameras": {"image_primary": ["agentview", 84]}},
        policy={"dataset_key": "robosuite_ft", "proprio_normalization": "bounds", "sampler": "v0.1.0"},
    )
    path = conventions.write(tmp_path)
    assert path.name == "harness.toml"
    read = CheckpointConventions.read(tmp_path)
    env = read.env_options({"masks": True, "image_convention": None})  # None = not given by the user
    assert env == EnvOptions(masks=True, cameras=(("image_primary", "agentview", 84),), image_convention="opengl",
                             action_space="robosuite")
    assert read.env_options({"action_space": "octo-delta"}).action_space == "octo-delta"  # the user's flag wins
    policy = read.policy_config({"execution": "receding_horizon"})
    assert (policy.dataset_key, policy.proprio_normalization, policy.sampler, policy.execution) == (
        "robosuite_ft", "bounds", "v0.1.0", "receding_horizon")
    assert CheckpointConventions.read(tmp_path / "missing").env_options() == EnvOptions()


def test_checkpoint_conventions_errors_name_the_file(tmp_path):
    (tmp_path / "harness.toml").write_text('[env]\naction_space = "delta"\n')
    with pytest.raises(ConventionsError, match="harness.toml: action space 'delta' unknown"):
        CheckpointConventions.read(tmp_path)
    (tmp_path / "harness.toml").write_text('[env]\nmasks = true\n')
    with pytest.raises(ConventionsError, match="not checkpoint conventions"):
        CheckpointConventions.read(tmp_path)
    (tmp_path / "harness.toml").write_text('[policy]\nsamplr = "latest"\n')
    with pytest.raises(ConventionsError, match="samplr"):
        CheckpointConventions.read(tmp_path)
    (tmp_path / "harness.toml").write_text('[policy\n')
    with pytest.raises(ConventionsError, match="not valid TOML"):
        CheckpointConventions.read(tmp_path)


# ------------------------------------------------------------------ image convention on a marked image


def test_opengl_convention_marked_image_and_token_map():
    """A red top-left corner (upright) is bottom-left for an opengl model; its attention maps back to the top."""
    upright = np.zeros((8, 8, 3), np.uint8)
    upright[:2, :2] = (255, 0, 0)  # red corner, top-left of what the user sees
    model_view = envs.to_convention(upright, "opengl")
    assert model_view[-2:, :2, 0].min() == 255 and model_view[:2, :2].max() == 0  # bottom-left for the model
    np.testing.assert_array_equal(envs.to_convention(model_view, "opengl"), upright)  # its own inverse
    np.testing.assert_array_equal(envs.to_convention(upright, "upright"), upright)

    tokens = build_token_map([], [("obs_primary", 4), ("readout_action", 1)], 1, (("obs_primary", "image_primary", 2, 2),))
    row = np.zeros(5)
    row[2] = 1.0  # the model's patch (1, 0): bottom-left of ITS view = the red corner
    assert A.camera_maps(row, tokens, "image_primary")[1, 0] == 1.0
    shown = A.camera_maps(row, tokens.with_rows_flipped(["image_primary"]), "image_primary")
    np.testing.assert_array_equal(shown, [[1.0, 0.0], [0.0, 0.0]])  # drawn on the red corner of the upright frame
    assert shown[0, 0] == 1.0 and upright[0, 0, 0] == 255


def test_lowdim_share_and_several_readouts_in_token_map():
    tokens = build_token_map(
        [("task_language", 2)],
        [("obs_primary", 4), ("obs_proprio", 3), ("obs_task_language", 2), ("readout_action", 1), ("readout_value", 2)],
        2,
        (("obs_primary", "image_primary", 2, 2),),
    )
    assert tokens.num_keys == 2 + 2 * 12
    assert list(tokens.readout_index) == [23, 24, 25]  # both readout groups of the last timestep
    rows = np.zeros((3, tokens.num_keys))
    rows[:, tokens.indices("obs_proprio")] = 0.1  # 6 keys over 2 timesteps
    rows[:, tokens.indices("obs_primary", 1)] = 0.1  # 4 keys
    metrics = A.step_metrics(rows.reshape(1, 1, 3, -1), tokens)
    np.testing.assert_allclose(metrics["share/lowdim"], [0.6])
    np.testing.assert_allclose(metrics["share/primary"], [0.4])
    assert "share/other" not in metrics


# ------------------------------------------------------------------ low-dim history window


def test_episode_state_windows_and_pads_lowdim_like_images():
    from harness.policy import EnvMismatchError, EpisodeState, PolicyConfig, TaskPrompt

    state = EpisodeState({"image_primary": (4, 4)}, 2, 1, PolicyConfig(), TaskPrompt.of("x"), 0, {"proprio": 3})
    first = {"image_primary": np.zeros((4, 4, 3), np.uint8), "proprio": np.array([1.0, 2.0, 3.0])}
    request = state.observe(first)
    obs = request.observation
    np.testing.assert_array_equal(obs["proprio"], [[1, 2, 3], [1, 2, 3]])  # left-padded with the first observation
    np.testing.assert_array_equal(obs["timestep_pad_mask"], [False, True])
    np.testing.assert_array_equal(obs["pad_mask_dict"]["proprio"], [False, True])
    assert obs["proprio"].dtype == np.float32 and obs["image_primary"].shape == (2, 4, 4, 3)
    with pytest.raises(EnvMismatchError, match="'proprio' as 3-D but the env gives 8-D"):
        state.observe({"image_primary": first["image_primary"], "proprio": np.zeros(8)})
    with pytest.raises(EnvMismatchError, match=r"camera observation\(s\) \['image_primary'\]"):
        state.observe({"proprio": np.zeros(3)})


# ------------------------------------------------------------------ writers with any set of token groups


def test_writer_takes_the_token_map_from_the_records_and_handles_proprio_one_camera_two_readouts(tmp_path):
    """No language, one camera, a proprio group and two readout groups; the writer is given no token map."""
    from harness.records import EpisodeMeta, StepRecord
    from harness.outputs.writers import EpisodeWriter, OutputOptions

    tokens = build_token_map([], [("obs_primary", 16), ("obs_proprio", 8), ("readout_action", 1), ("readout_value", 1)],
                             1, (("obs_primary", "image_primary", 4, 4),))
    rng = np.random.default_rng(0)
    meta = EpisodeMeta(run="t", task="Lift", episode=0, seed=0, instruction="", model="built", model_is_random=True,
                       dataset_key=None, text_tokenizer="none", execution="temporal_ensemble")
    writer = EpisodeWriter(tmp_path / "ep", None, meta, OutputOptions(video=False))
    for t in range(2):
        target = np.zeros((64, 64), bool)
        target[:16, :16] = True
        writer.add_step(StepRecord(
            step=t, frames={"image_primary": rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)},
            readout_attention=rng.dirichlet(np.ones(26), size=(2, 4, 2)).astype(np.float32),
            actions_predicted=np.zeros((3, 7), np.float32), action_executed=np.zeros(7, np.float32), reward=0.0,
            success=False, masks={"image_primary": {"target": target, "robot": ~target}}, tokens=tokens))
    writer.finish({})
    ep = tmp_path / "ep"
    assert sorted(p.name for p in ep.glob("*.png")) == [f"step_{t:04d}_layer_{l:02d}.png" for t in range(2) for l in range(2)]
    with np.load(ep / "attention.npz") as z:
        assert list(z["tokens/group"]).count("obs_proprio") == 8 and z["readout_attention"].shape == (2, 2, 4, 2, 26)
        shares = sum(z[f"metrics/share/{k}"] for k in ("primary", "lowdim", "readout"))
        np.testing.assert_allclose(shares, 1.0, atol=1e-5)
        assert "metrics/share/language" in z.files and np.all(z["metrics/share/language"] == 0)

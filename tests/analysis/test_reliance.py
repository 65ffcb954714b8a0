"""Region reliance (harness/probes/reliance/measure.py; nuisance reliance: harness/probes/reliance/reader.py): stand-in
policies whose answer is known, the region table, nuisance reliance, the per-step hook of the policy, and one real
step of the tiny model on Lift."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from harness.policies import as_policy
from harness.probes.reliance import reader as N
from harness.probes.reliance import measure as R
from harness.policy import EnvMismatchError, EpisodeState, InferenceRequest, PolicyConfig, TaskPrompt

SIZE = 16
HORIZON, DIM = 4, 7


def toy_masks() -> dict[str, np.ndarray]:
    """robosuite's mask names on a 16x16 frame: target rows 2-5 x cols 2-5, gripper rows 8-11 x cols 8-11 (robot =
    gripper + arm), arm rows 12-15 x cols 0-3, an empty goal, one distractor rows 0-1 x cols 12-15, background the rest."""
    target = np.zeros((SIZE, SIZE), bool)
    target[2:6, 2:6] = True
    gripper = np.zeros_like(target)
    gripper[8:12, 8:12] = True
    arm = np.zeros_like(target)
    arm[12:16, 0:4] = True
    distractor = np.zeros_like(target)
    distractor[0:2, 12:16] = True
    goal = np.zeros_like(target)
    background = ~(target | gripper | arm | distractor)
    return {"target": target, "robot": gripper | arm, "gripper": gripper, "arm": arm, "goal": goal,
            "distractor_0": distractor, "background": background}


def toy_images(seed: int = 0, window: int = 2) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {key: rng.uniform(0, 255, (window, SIZE, SIZE, 3)).astype(np.float32) for key in ("image_primary", "image_wrist")}


def reader(weights: dict[str, float], camera: str = "image_primary"):
    """A stand-in policy: the chunk is sum_r weight_r * (mean pixel of region r of `camera`'s current frame),
    broadcast over (horizon, dim): it reads those regions and nothing else."""
    masks = toy_masks()

    def evaluate(inputs: dict) -> np.ndarray:
        frames = np.asarray(inputs[camera], np.float64)[:, -1]  # (m, H, W, 3)
        value = sum((w * frames[:, masks[r]].mean(axis=(1, 2)) for r, w in weights.items()), np.zeros(len(frames)))
        return np.broadcast_to(value[:, None, None], (len(value), HORIZON, DIM)) + np.linspace(0, 1, HORIZON * DIM).reshape(HORIZON, DIM)

    return evaluate


def by_region(rows, camera="image_primary") -> dict[str, dict]:
    return {r["region"]: r for r in rows if r["camera"] == camera}


@pytest.mark.parametrize("fill", ["mean", "blur", "impute"])
def test_a_policy_reading_one_region_gives_it_all_the_reliance(fill):
    images = toy_images()
    masks = {"image_primary": toy_masks(), "image_wrist": toy_masks()}
    rows = R.region_reliance(reader({"target": 1.0}), images, masks, fill=fill, grids={k: (4, 4) for k in images}, step=3)
    primary = by_region(rows)
    assert list(primary) == ["target", "gripper", "arm", "goal", "distractors", "background"]  # the table's order
    assert primary["target"]["change"] > 1.0 and primary["target"]["reliance_share"] == 1.0
    assert all(r["change"] == 0.0 and r["reliance_share"] == 0.0 for name, r in primary.items() if name != "target")
    if fill != "impute":  # mean and blur fill a pixel alike whatever else is replaced: the whole camera = the target
        assert primary["target"]["camera_change"] == pytest.approx(primary["target"]["change"], rel=1e-9)
    else:  # imputation continues the region's surroundings, which the whole camera loses too
        assert primary["target"]["camera_change"] > 1.0
    assert primary["target"]["reliance_per_pixel"] == pytest.approx(primary["target"]["change"] / (16 / 256))
    wrist = by_region(rows, "image_wrist")  # a camera the policy does not read: no change, no shares
    assert all(r["change"] == 0.0 and r["reliance_share"] is None and r["camera_change"] == 0.0 for r in wrist.values())
    assert {r["step"] for r in rows} == {3} and {r["fill"] for r in rows} == {fill}


def test_two_regions_read_with_known_weights_share_in_that_ratio():
    images = toy_images()
    masks = toy_masks()
    for key in images:  # both read regions hold the same pixels, so one fill moves each mean alike
        images[key][-1][masks["target"]] = 200.0
        images[key][-1][masks["gripper"]] = 200.0
    rows = R.region_reliance(reader({"target": 3.0, "gripper": 1.0}), images, {"image_primary": masks}, fill="mean")
    primary = by_region(rows)
    assert primary["target"]["reliance_share"] == pytest.approx(0.75, abs=1e-12)
    assert primary["gripper"]["reliance_share"] == pytest.approx(0.25, abs=1e-12)
    assert primary["target"]["change"] == pytest.approx(3 * primary["gripper"]["change"], rel=1e-12)
    assert primary["background"]["reliance_share"] == 0.0
    assert {r["camera"] for r in rows} == {"image_primary"}  # the wrist camera has no masks: no rows


def test_empty_regions_give_null_per_pixel_reliance_not_an_error():
    images = toy_images()
    masks = toy_masks()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a division by zero would warn
        rows = R.region_reliance(reader({"target": 1.0}), images, {"image_primary": masks}, fill="impute")
        goal = by_region(rows)["goal"]
        assert goal["area_fraction"] == 0.0 and goal["change"] == 0.0 and goal["reliance_per_pixel"] is None
        assert goal["reliance_share"] == 0.0
        unread = R.region_reliance(reader({}), images, {"image_primary": masks}, fill="mean")  # reads nothing
    assert all(r["reliance_share"] is None and r["change"] == 0.0 for r in unread)
    assert by_region(unread)["goal"]["reliance_per_pixel"] is None
    assert by_region(unread)["target"]["reliance_per_pixel"] == 0.0
    assert math.isnan(N.step_nuisance(unread)[(0, "image_primary")]["nuisance_reliance"])
    with pytest.raises(ValueError, match="unknown reliance fill 'noise'; use one of mean, blur, impute"):
        R.region_reliance(reader({}), images, {"image_primary": masks}, fill="noise")


def test_one_call_holds_the_step_and_every_variant():
    calls = []

    def counted(inputs):
        calls.append(len(inputs["image_primary"]))
        return reader({"target": 1.0, "background": 0.5})(inputs)

    masks = {"image_primary": toy_masks(), "image_wrist": toy_masks()}
    batched = R.region_reliance(counted, toy_images(), masks, fill="mean")
    # the step + per camera 5 regions with pixels (goal has none) + the whole camera: 13, padded to 16
    assert calls == [16]
    calls.clear()
    single = R.region_reliance(counted, toy_images(), masks, fill="mean", per_call=1)
    assert calls == [1] * 13 and single == batched


def test_the_region_table_partitions_robosuite_and_libero_masks():
    masks = toy_masks()
    masks["distractor_1"] = np.zeros((SIZE, SIZE), bool)
    masks["distractor_1"][15, 15] = True
    masks["background"][15, 15] = False
    regions = R.region_masks(masks)
    assert list(regions) == ["target", "gripper", "arm", "goal", "distractors", "background"]  # robot: gripper + arm
    assert regions["distractors"].sum() == 8 + 1
    stacked = np.stack(list(regions.values())).astype(int)
    assert (stacked.sum(axis=0) == 1).all()  # disjoint, every pixel in one region
    # a task object robosuite labels in no mask: the remainder, under task_objects
    masks["background"][0, 0] = False
    assert R.region_masks(masks)[R.TASK_OBJECTS].sum() == 1
    # LIBERO: target, robot, distractors, object.<name> (overlapping); no background mask: the rest is background
    libero = {"target": masks["target"], "robot": masks["robot"], "distractors": masks["distractor_0"],
              "object.bowl_1": masks["target"]}
    regions = R.region_masks(libero, (2 * SIZE, 2 * SIZE))  # resized to the model's frame
    assert list(regions) == ["target", "robot", "distractors", "background"]
    assert regions["target"].shape == (32, 32) and regions["target"].sum() == 4 * 16
    np.testing.assert_array_equal(R.resize_mask(masks["target"], (8, 8))[1:3, 1:3], True)
    assert R.resize_mask(masks["target"], (8, 8)).sum() == 4


def test_nuisance_reliance_known_answer():
    def row(step, region, share, camera="image_primary"):
        return {"step": step, "camera": camera, "region": region, "reliance_share": share}

    rows = [row(0, "target", 0.5), row(0, "background", 0.25), row(0, "distractors", 0.25),
            row(4, "target", None), row(4, "background", None),  # nothing used at step 4: nan, left out of the means
            row(12, "target", 0.25), row(12, "background", 0.75),
            row(0, "background", 1.0, "image_wrist")]  # another camera
    per_step = N.step_nuisance(rows)
    assert per_step[(0, "image_primary")] == {"nuisance_reliance": 0.5, "background_reliance": 0.25,
                                              "distractor_reliance": 0.25}
    assert per_step[(0, "image_wrist")]["nuisance_reliance"] == 1.0
    episode = N.nuisance_reliance(rows)
    assert episode["step"] == [0, 4, 12] and episode["per_step"][0] == 0.5 and math.isnan(episode["per_step"][1])
    assert episode["nuisance_reliance"] == pytest.approx(0.625) and episode["background_reliance"] == pytest.approx(0.5)
    assert episode["distractor_reliance"] == pytest.approx(0.125)
    assert episode["nuisance_reliance_start"] == 0.5  # steps before START_STEPS (10): step 0 only
    assert math.isnan(N.nuisance_reliance(rows, "image_side")["nuisance_reliance"])


def test_the_policy_hook_is_off_by_default_and_sends_masks_only_at_its_steps():
    assert "reliance_every" not in PolicyConfig().to_dict() and "reliance_fill" not in PolicyConfig().to_dict()
    assert PolicyConfig(reliance_every=4, reliance_fill="mean").to_dict()["reliance_every"] == 4
    for bad, message in (({"reliance_every": -1}, "--reliance-every must be an integer >= 0"),
                         ({"reliance_every": True}, "--reliance-every must be an integer >= 0"),
                         ({"reliance_fill": "noise"}, "--reliance-fill must be 'mean', 'blur' or 'impute'")):
        with pytest.raises(ValueError, match=message):
            PolicyConfig(**bad)
    obs = {"image_primary": np.zeros((SIZE, SIZE, 3), np.uint8)}
    masks = {"image_primary": toy_masks()}

    def requests(config, n=3, masks=masks):
        state = EpisodeState({"image_primary": (SIZE, SIZE)}, 2, HORIZON, config, TaskPrompt.of("lift"), 0)
        out = []
        for _ in range(n):
            request = state.observe(obs, masks)
            assert isinstance(request, InferenceRequest)
            out.append(request)
            state.t += 1
        return out

    assert [r.masks for r in requests(PolicyConfig())] == [None] * 3  # off: nothing travels
    assert [r.masks is masks for r in requests(PolicyConfig(reliance_every=2))] == [True, False, True]
    with pytest.raises(EnvMismatchError, match="needs the env's masks at every reliance step; drop --no-masks") as e:
        requests(PolicyConfig(reliance_every=2), masks=None)
    assert "\n" not in str(e.value)


@pytest.mark.slow
def test_one_real_lift_step_of_the_tiny_model(fixtures_dir):
    """Real masks of a Lift step (128 px renders, resized to the model's 64 and 32 px), the tiny model through the
    closed loop's hook: every labelled region reported per camera, bit-identical twice and outside the loop."""
    import envs
    from harness.octo import load_pretrained

    from harness.rollout import rollout

    model = load_pretrained(str(fixtures_dir / "tiny"))
    env = envs.make("Lift", cameras={"image_primary": ("agentview", 128), "image_wrist": ("robot0_eye_in_hand", 128)},
                    fast_render=True, masks=True)
    try:
        policy = as_policy(model).closed_loop(PolicyConfig(reliance_every=4))
        runs = []
        for _ in range(2):
            records = []
            rollout(env, policy, records.append, seed=0, max_steps=1)
            runs.append(records)
        obs, info = env.reset(seed=0)
    finally:
        env.close()
    rows = runs[0][0].probes["reliance"]["rows"]
    assert rows == runs[1][0].probes["reliance"]["rows"]  # deterministic: the same step twice gives the same record
    for key, (height, width) in model.image_sizes.items():
        expected = R.region_masks(info["masks"][key], (height, width))
        camera = by_region(rows, key)
        assert list(camera) == list(expected) == ["target", "gripper", "arm", "background"]
        for name, row in camera.items():
            assert set(row) == {"step", "camera", "region", "fill", "change", "area_fraction", "reliance_per_pixel",
                                "reliance_share", "camera_change"}
            assert row["fill"] == "impute" and row["step"] == 0 and row["change"] >= 0
            assert row["area_fraction"] == pytest.approx(float(expected[name].mean()))
        assert sum(r["area_fraction"] for r in camera.values()) == pytest.approx(1.0)
        shares = [r["reliance_share"] for r in camera.values() if r["reliance_share"] is not None]
        assert len(shares) == len(camera) and sum(shares) == pytest.approx(1.0)
        assert camera["background"]["camera_change"] > 0
    # the batched call of the closed loop again, outside it: the same rows (one call per variant is checked with
    # stand-in policies above; a second compiled batch shape of the real model costs a cold compile in CI)
    policy.reset(info["instruction"], seed=0)
    request = policy._state.observe(obs, info["masks"])
    inference = policy._infer
    observations, tasks, keys = inference._inputs([request])
    assert inference.probe("reliance").regions(observations, tasks, keys[0], 0, 0, request.masks)["rows"] == rows

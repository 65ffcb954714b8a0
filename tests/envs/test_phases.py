"""Task phases from the simulator's privileged state (envs/phases.py) and the gripper, arm and goal masks.

Known answers:
- driven by the scripted experts (reference_policies/experts.py), the phases appear in order and each boundary falls
  within BOUNDARY_STEPS steps of the expert's own phase switch (approach -> grasp: the expert's "close"; grasp ->
  lift/transport: its "lift"; transport -> place: its "lower"; place -> release: its "release"); a successful
  episode reaches the last phase;
- a random-weights policy rarely leaves approach;
- the gripper mask lies inside the old robot mask (gripper and arm split it), and the goal mask never overlaps the
  target at reset;
plus the phase rules, the per-phase means, event alignment and the paired test on hand-made inputs (Friedman's
statistic for identical rankings is n (k - 1), p = exp(-n (k-1) / 2) for k = 3).
"""

import json
import math

import numpy as np
import pytest

import envs
from envs.phases import LIFT, PICK_PLACE, PHASE_SPECS, PhaseState, phase_names, phase_of
from envs.segmentation import GOAL, GRIPPER, ROBOT, TARGET, geom_categories, masks_from_segmentation, scene_lookup
from harness.analysis import phases as P
from reference_policies.experts import ScriptedExpert

BOUNDARY_STEPS = 8  # measured: 1-7 steps (the fingers take ~7 steps to close; the expert's carry ends 5-7 steps
# after the object is over its goal; the fingers let go ~6 steps into the expert's release)
EXPERT_SWITCH = {"grasp": "close", "lift": "lift", "transport": "lift", "place": "lower", "release": "release"}


# ---- phase rules and analysis on hand-made inputs ------------------------------------------------------------------


def test_phase_rules():
    assert phase_of(LIFT, PhaseState(False, 0.0)) == "approach"
    assert phase_of(LIFT, PhaseState(True, 0.002)) == "grasp"
    assert phase_of(LIFT, PhaseState(True, 0.03)) == "lift"
    cases = [(PhaseState(False, 0.0), "approach"), (PhaseState(True, 0.0), "grasp"),
             (PhaseState(True, 0.05), "transport"), (PhaseState(False, 0.05), "transport"),  # dropped mid-air
             (PhaseState(True, 0.05, over_goal=True), "place"), (PhaseState(False, 0.05, over_goal=True), "release"),
             (PhaseState(False, 0.0, over_goal=True, on_goal=True), "release"),
             (PhaseState(False, 0.0, over_goal=True), "approach")]  # over the goal at rest height, untouched
    for state, phase in cases:
        assert phase_of(PICK_PLACE, state) == phase, state
    assert phase_names("Lift") == LIFT and phase_names("Door") == () and phase_names("PickPlace") == ()
    for task in PHASE_SPECS:
        envs.get_task(task)  # every phase function belongs to a registered task


def test_gripper_and_goal_categories():
    names = ["world", "robot0_base", "robot0_right_hand", "gripper0_finger", "cube_main", "bin2", "table"]
    parents = np.array([0, 0, 1, 2, 0, 0, 0])
    categories = geom_categories(np.arange(7), names, parents, ("cube_",), ("robot0_", "gripper0_"),
                                 ("robot0_right_hand", "gripper0_"), ("bin2",))
    np.testing.assert_array_equal(categories, [0, ROBOT, GRIPPER, GRIPPER, TARGET, GOAL, 0])
    table = scene_lookup(np.arange(7), np.full(7, 5), np.arange(7), categories)
    ids = np.arange(1, 8)[None]
    rgb = np.stack([ids & 255, (ids >> 8) & 255, ids >> 16], axis=-1).astype(np.uint8)
    masks = masks_from_segmentation(rgb, table, gripper=True, goal=True)
    np.testing.assert_array_equal(masks["robot"][0], [0, 1, 1, 1, 0, 0, 0])  # the old robot mask, gripper included
    np.testing.assert_array_equal(masks["gripper"][0], [0, 0, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(masks["arm"][0], [0, 1, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(masks["goal"][0], [0, 0, 0, 0, 0, 1, 0])
    assert set(masks_from_segmentation(rgb, table)) == {"target", "robot"}


def test_phase_means_onsets_and_alignment():
    phase = np.array([0, 0, 0, 1, 1, 2, 2, 2])
    values = np.arange(8.0)[:, None] * np.array([1.0, 10.0])  # (steps, layers)
    means = P.phase_means(phase, values, 4)
    np.testing.assert_allclose(means[:3], [[1, 10], [3.5, 35], [6, 60]])
    assert np.isnan(means[3]).all()  # never in phase 3
    assert P.onsets(phase, PICK_PLACE) == {"grasp onset": 3, "lift-off": 5}
    aligned = P.align(values, 3, 4)
    assert aligned.shape == (9, 2) and np.isnan(aligned[0]).all() and aligned[4, 0] == 3 and aligned[8, 0] == 7
    assert np.isnan(P.align(values, 6, 4)[-1]).all()


def test_phase_test_against_closed_forms():
    n = 6
    rising = np.tile([1.0, 2.0, 3.0], (n, 1)) + np.arange(n)[:, None] * 0.1  # every episode ranks the phases alike
    t = P.phase_test(rising)
    assert t.test == "friedman" and t.episodes == n and t.phases == (0, 1, 2)
    assert t.statistic == pytest.approx(n * 2) and t.p == pytest.approx(math.exp(-n))  # chi2, 2 df: exp(-x/2)
    flat = np.ones((5, 3))
    assert P.phase_test(flat).p == 1.0
    two = np.column_stack([np.arange(8.0), np.arange(8.0) + 1 + np.linspace(0, 0.7, 8)])
    w = P.phase_test(np.column_stack([two, np.full(8, np.nan)]))  # a phase nobody visited is dropped
    assert w.test == "wilcoxon" and w.phases == (0, 1) and w.p == pytest.approx(2 / 2 ** 8)  # exact: all 8 signs agree
    assert P.phase_test(np.full((2, 3), 1.0)).test == "none"  # too few episodes
    fm, sm, p, nf, ns = P.failure_contrast([1.0, 2.0, np.nan], [5.0, 6.0, 7.0])
    assert (fm, sm, nf, ns) == (1.5, 6.0, 2, 3) and p == pytest.approx(0.2)  # exact Mann-Whitney: 2 of C(5,2)=10


def test_phase_lifts_background_is_what_no_mask_covers():
    steps, layers = 2, 1
    arrays = {}
    for name, mass, area in (("target", 0.2, 0.1), ("robot", 0.3, 0.3), ("gripper", 0.1, 0.05), ("goal", 0.1, 0.1)):
        arrays[f"measures/layer/mask_mass/cam/{name}"] = np.full((steps, layers), mass)
        arrays[f"metrics/mask_area/cam/{name}"] = np.full(steps, area)
    lifts = P.phase_lifts(arrays)
    assert lifts["cam/target"][0, 0] == pytest.approx(2.0) and lifts["cam/gripper"][0, 0] == pytest.approx(2.0)
    assert lifts["cam/background"][0, 0] == pytest.approx(0.4 / 0.5)
    assert "cam/robot" not in lifts


# ---- the simulator ---------------------------------------------------------------------------------------------------


def _expert_episode(task: str, seed: int, max_steps: int = 300):
    env = envs.make(task, masks=False, action_space="robosuite", fast_render=True, cameras={})
    try:
        obs, info = env.reset(seed=seed)
        expert = ScriptedExpert(task)
        expert.reset(obs, env.unwrapped)
        trace = []  # (step, expert phase, env phase of the state acted on)
        for t in range(max_steps):
            action = expert.act(obs, env.unwrapped)
            trace.append((t, expert.phase, info["phase"]))
            obs, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                break
        trace.append((t + 1, "end", info["phase"]))  # the final state counts for the furthest phase
        return trace, bool(info["success"])
    finally:
        env.close()


@pytest.mark.slow
@pytest.mark.parametrize("task,seed", [("Lift", 0), ("Stack", 1), ("PickPlaceCan", 2)])
def test_expert_drives_the_phases_in_order_near_its_own_switches(task, seed):
    trace, success = _expert_episode(task, seed)
    names = phase_names(task)
    indices = [names.index(p) for _, _, p in trace]
    assert indices == sorted(indices), f"phases out of order: {[p for _, _, p in trace]}"
    assert success and indices[-1] == len(names) - 1  # a successful episode reaches the last phase
    for k, phase in enumerate(names[1:], start=1):
        onset = next(t for t, _, p in trace if names.index(p) >= k)
        switch = next(t for t, e, _ in trace if e == EXPERT_SWITCH[phase])
        assert abs(onset - switch) <= BOUNDARY_STEPS, f"{phase} at step {onset}, the expert's {EXPERT_SWITCH[phase]} at {switch}"


@pytest.mark.slow
@pytest.mark.parametrize("task", ["Stack", "PickPlaceCan"])
def test_gripper_inside_robot_and_goal_apart_from_target_at_reset(task):
    env = envs.make(task, masks=True, fast_render=True)
    try:
        for seed in range(3):
            _, info = env.reset(seed=seed)
            assert info["phase"] == "approach"
            for camera, masks in info["masks"].items():
                robot, gripper, arm = masks["robot"], masks["gripper"], masks["arm"]
                assert not (gripper & ~robot).any(), camera  # the gripper lies inside the old robot mask
                assert np.array_equal(gripper | arm, robot) and not (gripper & arm).any()
                assert not (masks["goal"] & masks["target"]).any(), camera
            primary = info["masks"]["image_primary"]
            assert primary["gripper"].sum() > 100 and primary["goal"].sum() > 100 and primary["target"].sum() > 50
    finally:
        env.close()


@pytest.mark.slow
def test_every_phase_task_gives_a_phase_and_others_none():
    for task in ("NutAssemblySquare", "PickPlaceMilk", "Door"):
        env = envs.make(task, cameras={})
        try:
            _, info = env.reset(seed=0)
            assert info["phase"] == ("approach" if task in PHASE_SPECS else None), task
        finally:
            env.close()


@pytest.mark.slow
def test_a_random_weights_policy_rarely_leaves_approach(tmp_path):
    from harness.cli import main

    model = "random:" + str(envs.__file__).rsplit("/envs/", 1)[0] + "/models/octo-reference-robosuite"
    code = main(["run", "--model", model, "--task", "Lift", "--episodes", "3", "--seed", "0", "--max-steps", "40",
                 "--png-every", "0", "--no-video", "--fast-render", "--no-masks", "--out", str(tmp_path),
                 "--run-name", "random"])
    assert code == 0
    rows = [json.loads(line) for line in (tmp_path / "random" / "results.jsonl").read_text().splitlines()]
    assert len(rows) == 3 and all(r["status"] == "ok" for r in rows)
    assert sum(r["furthest_phase"] == "approach" for r in rows) >= 2
    phases = []
    for r in rows:
        with open(tmp_path / "random" / r["directory"] / "metrics.jsonl") as f:
            phases += [json.loads(line)["phase"] for line in f]
        summary = json.loads((tmp_path / "random" / r["directory"] / "episode.json").read_text())["phases"]
        assert summary["names"] == list(LIFT) and sum(summary["steps"].values()) == r["steps"]
    assert np.mean([p == "approach" for p in phases]) >= 0.9

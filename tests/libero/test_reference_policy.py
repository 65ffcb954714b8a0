"""The LIBERO-Object reference policy (issue 32): demonstrations from sampled placements (never the stored evaluation
states), the picked object read from the simulator, paraphrases and the named object, the trainer's LIBERO
conventions, and the grounding measures with known answers (quick ones on synthetic episodes; the LIBERO ones start
the real LIBERO environment and are marked slow, as in tests/libero/test_libero_env.py)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import envs
from envs import libero_tasks
from harness.analysis import grounding as G
from tests.helpers import needs_libero as _needs_libero  # skips outside CI, fails under CI=true, without LIBERO

REPO = Path(__file__).resolve().parents[2]
MODEL = REPO / "models" / "octo-reference-libero-object"  # the second recipe's policy (issue 46)
# the first recipe's policy (the reference until issue 46), kept as the lever table's "first" row
FIRST = REPO / "models" / "octo-reference-libero-object-first"
# the trainer's default sizes (the synthetic frames below): the first LIBERO policy's cameras
WRIST_64 = (("image_primary", "agentview", 128), ("image_wrist", "robot0_eye_in_hand", 64))


# ------------------------------------------------------------------------------------------------ quick, no LIBERO


def test_libero_object_paraphrases_name_the_same_object_and_other_suites_have_none():
    for i in range(10):
        spec = envs.get_task(f"libero_object/{i}")
        words = libero_tasks.named_object(spec.instruction)
        assert words and spec.targets[0].startswith(words.replace(" ", "_"))
        assert len(spec.paraphrases) == 4 and len(set(spec.paraphrases)) == 4
        assert all(libero_tasks.named_object(p) == words for p in spec.paraphrases)
    assert envs.get_task("libero_spatial/0").paraphrases == ()
    assert libero_tasks.named_object("open the top drawer of the cabinet") is None
    assert libero_tasks.named_object("blorp the zizzle quantum") is None


def test_instance_of_and_grasp_step_known_answers():
    objects = ("alphabet_soup_1", "basket_1", "cream_cheese_1", "milk_1")
    assert G.instance_of("alphabet soup", objects) == "alphabet_soup_1"
    assert G.instance_of("milk", objects) == "milk_1"
    assert G.instance_of("orange juice", objects) is None  # not in this scene
    assert G.instance_of(None, objects) is None
    executed = np.zeros((6, 7), np.float32)
    executed[:, 6] = [1, 1, 1, 0, 0, 1]
    assert G.grasp_step(executed) == 3
    executed[:, 6] = 1
    assert G.grasp_step(executed) == -1
    assert G.grasp_step(np.zeros((0, 7))) == -1


def _episode(folder: Path, instruction: str, picked, masses: dict[str, list[float]], areas: dict[str, float],
             gripper: list[float], layers: int = 2) -> Path:
    """A synthetic LIBERO episode folder: attention.npz object measures (same mass at every layer), actions.npz,
    episode.json with the instruction and the outcome."""
    folder.mkdir(parents=True)
    steps = len(gripper)
    arrays = {}
    for name, mass in masses.items():
        arrays[f"measures/layer/mask_mass/image_primary/object.{name}"] = np.repeat(
            np.asarray(mass, np.float32)[:, None], layers, axis=1)
        arrays[f"metrics/mask_area/image_primary/object.{name}"] = np.full(steps, areas[name], np.float32)
    np.savez(folder / "attention.npz", **arrays)
    executed = np.zeros((steps, 7), np.float32)
    executed[:, 6] = gripper
    np.savez(folder / "actions.npz", executed=executed)
    (folder / "episode.json").write_text(json.dumps({"instruction": instruction,
                                                     "outcome": {"picked_object": picked}}))
    return folder


def _record(name: str, task: str, folders: list[Path], success: list[bool]):
    episodes = tuple(SimpleNamespace(task=task, episode=k, seed=k, status="ok", ok=True, success=s, directory=f,
                                     attention_path=f / "attention.npz") for k, (f, s) in enumerate(zip(folders, success)))
    return SimpleNamespace(name=name, tasks=(task,), episodes=episodes)


def test_grounding_measures_known_answers(tmp_path):
    """Task 0's scene: the named object (alphabet soup) holds 0.3 of the mass on 0.05 of the image (lift 6) up to
    the grasp at step 2, cream cheese 0.1 on 0.05 (lift 2), the basket 0.5 on 0.1; after the grasp the soup and the
    cream cheese swap, which must not count.
    A swap to cream cheese that picks the cream cheese is a hit; the language-blind rate of that swap is how often the
    own-instruction episodes (same seeds) picked the cream cheese: 0 of 2."""
    own = envs.get_task("libero_object/0").instruction
    swapped = envs.get_task("libero_object/1").instruction  # cream cheese
    areas = {"alphabet_soup_1": 0.05, "cream_cheese_1": 0.05, "basket_1": 0.1}
    masses = {"alphabet_soup_1": [0.3, 0.3, 0.3, 0.05], "cream_cheese_1": [0.1, 0.1, 0.1, 0.6], "basket_1": [0.5] * 4}
    folders = [_episode(tmp_path / f"own{k}", own, "alphabet_soup_1", masses, areas, [1, 1, 0, 0]) for k in range(2)]
    swap_folders = [_episode(tmp_path / "swap0", swapped, "cream_cheese_1", masses, areas, [1, 1, 0, 0]),
                    _episode(tmp_path / "swap1", swapped, "alphabet_soup_1", masses, areas, [1, 1, 1, 1])]
    records = [_record("own", "libero_object/0", folders, [True, True]),
               _record("swap", "libero_object/0", swap_folders, [False, True])]
    rows, notes = G.collect(records)
    assert not notes and len(rows) == 4
    assert [r.grasp_step for r in rows] == [2, 2, 2, -1]
    summary, per_object = G.lift_rows(rows)
    last = [s for s in summary if s[0] == "own" and s[3] == 1][0]
    # the basket (the goal, named too) holds more mass than the alphabet soup but is neither named nor "other"
    assert last[4] == 2 and last[5] == pytest.approx(6.0) and last[6] == pytest.approx(2.0)
    assert last[7] == pytest.approx(2.0) and (last[9], last[10]) == (2, 2)  # named on top at the grasp in both
    roles = {o[4]: o[5] for o in per_object if o[0] == "own" and o[3] == 0}
    assert roles == {"alphabet_soup_1": "named", "cream_cheese_1": "other", "basket_1": "goal"}
    named = [o for o in per_object if o[0] == "own" and o[3] == 0 and o[5] == "named"]
    assert [o[4] for o in named] == ["alphabet_soup_1"]
    swaps = {s[0]: s for s in G.swap_rows(rows)}
    assert swaps["own"][3] == "own" and swaps["own"][5] == 2 and swaps["own"][4] == 2
    s = swaps["swap"]
    assert s[3] == "swap" and (s[4], s[5], s[9], s[11]) == (2, 1, 1, 0)  # 1 named, 1 scene target, none 0
    assert s[12] == 0.0 and s[13] == 2  # blind: the own-instruction episodes never picked the cream cheese


def test_grounding_reads_foreign_episode_files_as_notes_not_crashes(tmp_path):
    own = envs.get_task("libero_object/0").instruction
    good = _episode(tmp_path / "good", own, None, {"alphabet_soup_1": [0.1], "milk_1": [0.1]},
                    {"alphabet_soup_1": 0.1, "milk_1": 0.1}, [1])
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "episode.json").write_text("[1, 2")
    rows, notes = G.collect([_record("r", "libero_object/0", [good, bad], [False, False])])
    assert len(rows) == 1 and rows[0].picked is None and rows[0].grasp_step == -1
    assert len(notes) == 1 and "episode_1: unreadable" in notes[0]


def test_libero_conventions_parse_and_name_the_libero_action_space(tmp_path):
    from harness.conventions import CheckpointConventions
    from reference_policies.libero_pipeline import DATASET_KEY, conventions_toml

    (tmp_path / "harness.toml").write_text(conventions_toml())
    conventions = CheckpointConventions.read(tmp_path)
    options = conventions.env_options()
    assert options.action_space == "libero" and options.image_convention == "rot180"
    assert options.camera_dict == {"image_primary": ("agentview", 128), "image_wrist": ("robot0_eye_in_hand", 128)}
    assert conventions.policy_config().dataset_key == DATASET_KEY


def _box(centre, size):
    centre, half = np.asarray(centre, float), np.asarray(size, float) / 2
    return {"low": centre - half, "high": centre + half}


def test_a_labeller_with_close_below_top_does_not_close_over_a_flat_object():
    """A 1.8 cm butter-like box: its grasp point (1.2 cm above its bottom) is 0.6 cm below its top, so the default
    1.2 cm band closes with the hand over the top; with close_below_top = 3 mm it descends there and closes lower."""
    from dataclasses import replace

    from reference_policies.libero_expert import CLOSED, OPEN, LiberoExpertConfig, LiberoObjectLabeller

    poses = {"butter_1": _box([0, -0.2, 0.009], [0.08, 0.04, 0.018]), "basket_1": _box([0, 0.25, 0.04], [0.2, 0.2, 0.08])}
    c = LiberoExpertConfig()
    grasp_z = c.floor_clearance
    above_top = np.array([0.0, -0.2, grasp_z + 0.01])  # 0.4 cm over the box
    assert LiberoObjectLabeller("butter_1").waypoint(above_top, 0.08, poses, held=False)[1] == CLOSED
    capped = LiberoObjectLabeller("butter_1", config=replace(c, close_below_top=0.003))
    goal, grip = capped.waypoint(above_top, 0.08, poses, held=False)
    assert grip == OPEN
    np.testing.assert_allclose(goal, [0, -0.2, grasp_z])  # down to the grasp point first
    assert capped.waypoint(np.array([0.0, -0.2, grasp_z + 0.002]), 0.08, poses, held=False)[1] == CLOSED


def test_recording_fingerprints_leave_out_close_below_top_while_it_is_off():
    """The field came after the committed recordings: off (None), fingerprints are as before, so those recordings
    stay reusable (the reference's summary equals the second recipe's fingerprint); set, it is part of them."""
    from dataclasses import replace

    from reference_policies.demos import config_fingerprint
    from reference_policies.libero_pipeline import RECIPES

    second = RECIPES["second"]
    assert "close_below_top" not in config_fingerprint(second)["expert"]
    summary = json.loads((MODEL / "training_summary.json").read_text())
    assert summary["demonstrations"]["config"] == config_fingerprint(second)
    capped = replace(second, expert=replace(second.expert, close_below_top=0.005))
    assert config_fingerprint(capped)["expert"]["close_below_top"] == 0.005
    assert config_fingerprint(capped) != config_fingerprint(second)


def test_the_labeller_reads_the_phase_off_the_state_known_answers():
    """LiberoObjectLabeller's waypoint for hand-made states: a 6 cm tall object at (0, -0.2) and a basket at (0, 0.25)
    whose rim is at 0.08 m."""
    from reference_policies.libero_expert import CLOSED, OPEN, LiberoExpertConfig, LiberoObjectLabeller

    c = LiberoExpertConfig()
    lab = LiberoObjectLabeller("soup_1")
    poses = {"soup_1": _box([0, -0.2, 0.03], [0.04, 0.04, 0.06]), "basket_1": _box([0, 0.25, 0.04], [0.2, 0.2, 0.08])}
    grasp_z = max(0.06 - c.finger_depth, 0.03, c.floor_clearance)
    open_fingers, empty = 0.08, 0.002
    # far and high: to the hover point above the object, open
    goal, grip = lab.waypoint(np.array([0.2, 0.0, 0.3]), open_fingers, poses, held=False)
    np.testing.assert_allclose(goal, [0, -0.2, 0.3])
    assert grip == OPEN
    # off-centre and low: straight up first
    goal, grip = lab.waypoint(np.array([0.05, -0.2, 0.05]), open_fingers, poses, held=False)
    np.testing.assert_allclose(goal, [0.05, -0.2, 0.06 + c.hover])
    # centred above: descend to the grasp point; at it: close
    goal, grip = lab.waypoint(np.array([0.0, -0.2, 0.2]), open_fingers, poses, held=False)
    np.testing.assert_allclose(goal, [0, -0.2, grasp_z])
    assert grip == OPEN
    assert lab.waypoint(np.array([0.0, -0.2, grasp_z + 0.005]), open_fingers, poses, held=False)[1] == CLOSED
    # closed on nothing beside the object: open and back up to the hover height
    goal, grip = lab.waypoint(np.array([0.04, -0.2, grasp_z]), empty, poses, held=False)
    assert grip == OPEN and goal[2] == pytest.approx(0.06 + c.hover)
    # held low beside the object: rise to the carrying height; held high: carry over the basket; over it: lower, open
    hand = np.array([0.0, -0.2, grasp_z])
    goal, grip = lab.waypoint(hand, 0.04, poses, held=True)
    carry_z = 0.08 + c.carry_clearance + (grasp_z - 0.0)
    assert grip == CLOSED and goal[:2].tolist() == [0.0, -0.2] and goal[2] == pytest.approx(carry_z)
    lifted = {**poses, "soup_1": _box([0, -0.2, carry_z - grasp_z + 0.03], [0.04, 0.04, 0.06])}  # moved with the hand
    goal, grip = lab.waypoint(np.array([0.0, -0.2, carry_z]), 0.04, lifted, held=True)
    np.testing.assert_allclose(goal[:2], [0, 0.25])
    assert grip == CLOSED
    over = {**poses, "soup_1": _box([0, 0.25, 0.2], [0.04, 0.04, 0.06])}
    hand = np.array([0.0, 0.25, 0.2 - 0.03 + grasp_z])  # the object hangs from the hand as it was grasped
    goal, grip = lab.waypoint(hand, 0.04, over, held=True)
    assert grip == CLOSED and goal[2] < hand[2]
    low = np.array([0.0, 0.25, 0.08 + c.release_above_rim + grasp_z])
    low_pose = {**poses, "soup_1": _box([0, 0.25, 0.08 + c.release_above_rim + 0.03], [0.04, 0.04, 0.06])}
    assert lab.waypoint(low, 0.04, low_pose, held=True)[1] == OPEN
    # released over the basket (falling in, not held): retreat upwards, open, never close on it again
    goal, grip = lab.waypoint(low, 0.05, low_pose, held=False)
    assert grip == OPEN and goal[2] > low[2]


def test_swapped_instruction_demonstrations_go_to_the_task_they_name(tmp_path):
    """append_swaps splits a scene's file by the task each episode named and appends those episodes to it,
    numbered after its own; an episode naming a task without demonstrations is refused in one line."""
    from reference_policies.libero_demos import append_swaps, swap_candidates

    assert swap_candidates("libero_object/8", ["chocolate_pudding_1", "basket_1", "orange_juice_1", "ketchup_1"]) == [
        "libero_object/9", "libero_object/4"]  # the order i+1, i+2, ... wraps round; the scene's own object is not one
    assert swap_candidates("libero_object/0", ["alphabet_soup_1", "basket_1"]) == []

    def frames(lengths, named=None, first=0.0):
        n = sum(lengths)
        out = {"action": first + np.arange(n, dtype=np.float32)[:, None] * np.ones((1, 7), np.float32),
               "episode": np.repeat(np.arange(len(lengths)), lengths).astype(np.int32),
               "step": np.concatenate([np.arange(k) for k in lengths]).astype(np.int32),
               "seeds": np.arange(len(lengths)) + 100, "lengths": np.array(lengths, np.int32)}
        if named is not None:
            out["named"] = np.repeat(named, lengths).astype(np.int32)
        return out

    np.savez(tmp_path / "libero_object_0.npz", **frames([2, 3, 1], named=[1, 2, 1], first=10.0))
    demos = {t: frames([1, 1]) for t in ("libero_object/0", "libero_object/1", "libero_object/2")}
    merged = append_swaps(demos, tmp_path, ("libero_object/0",))
    one, two = merged["libero_object/1"], merged["libero_object/2"]
    assert one["action"][:, 0].tolist() == [0, 1, 10, 11, 15] and one["episode"].tolist() == [0, 1, 2, 2, 3]
    assert one["seeds"].tolist() == [100, 101, 100, 102] and one["lengths"].tolist() == [1, 1, 2, 1]
    assert two["action"][:, 0].tolist() == [0, 1, 12, 13, 14] and two["step"].tolist() == [0, 0, 0, 1, 2]
    assert merged["libero_object/0"] is demos["libero_object/0"] and "named" not in one
    np.savez(tmp_path / "libero_object_0.npz", **frames([2], named=[5]))
    with pytest.raises(ValueError, match="names libero_object/5, which has no demonstrations"):
        append_swaps(demos, tmp_path, ("libero_object/0",))
    np.savez(tmp_path / "libero_object_0.npz", **frames([2], named=[99]))  # an edited file
    with pytest.raises(ValueError, match="names task number 99, which has no demonstrations"):
        append_swaps(demos, tmp_path, ("libero_object/0",))


def test_libero_dagger_seeds_are_their_own_block_and_bad_counts_are_refused():
    from reference_policies.libero_dagger import LIBERO_DAGGER_SEED_BASE, LiberoDaggerConfig
    from reference_policies.libero_demos import LIBERO_SEED_BASE, SEEDS_PER_JOB, LiberoDemoConfig

    demo = LiberoDemoConfig()
    demo_seeds = {demo.task_seed_base(t) + j * SEEDS_PER_JOB + k for t in demo.tasks
                  for j in range(demo.jobs_per_task) for k in range(SEEDS_PER_JOB)}
    config = LiberoDaggerConfig(episodes=50)
    dagger_seeds = {s for t in config.tasks for s in config.seeds(t)}
    assert len(dagger_seeds) == 500 and not dagger_seeds & demo_seeds
    assert min(dagger_seeds) == LIBERO_DAGGER_SEED_BASE > LIBERO_SEED_BASE
    with pytest.raises(ValueError, match="--dagger-episodes"):
        LiberoDaggerConfig(episodes=1)


def test_the_demonstrator_is_part_of_the_recording_fingerprint_and_unknown_ones_are_one_line():
    from reference_policies.demos import config_fingerprint
    from reference_policies.libero_demos import LiberoDemoConfig
    from reference_policies.libero_pipeline import main

    state, timed = LiberoDemoConfig(), LiberoDemoConfig(demonstrator="timed")
    assert state.demonstrator == "state"  # the second recipe's (issue 46); "timed" made the first committed policy
    assert config_fingerprint(timed) != config_fingerprint(state)  # a recording is never reused across them
    with pytest.raises(ValueError, match="use one of state, timed"):
        LiberoDemoConfig(demonstrator="scripted")
    with pytest.raises(SystemExit):
        main(["--demonstrator", "scripted"])


# ------------------------------------------------------------------------------------------------ LIBERO environment


@pytest.fixture(scope="module")
def camera_free_env():
    _needs_libero()
    env = envs.make("libero_object/0", cameras={}, action_space="libero")
    yield env
    env.close()


def test_the_grasp_probe_summary_known_answers_and_bad_arguments_are_one_line(tmp_path, capsys):
    from reference_policies import libero_probe

    rows = [dict(task="t/0", target="a", first_close=30, reach_xy_cm=1.0, held_named=True, lifted_named=True,
                 success=True, picked="a", nearest_at_close="a"),
            dict(task="t/0", target="a", first_close=40, reach_xy_cm=3.0, held_named=True, lifted_named=False,
                 success=False, picked="b", nearest_at_close="b"),
            dict(task="t/1", target="c", first_close=None, reach_xy_cm=None, held_named=False, lifted_named=False,
                 success=False, picked=None)]
    s = libero_probe.summarise(rows)
    assert (s["episodes"], s["successes"], s["closed"], s["median_reach_xy_cm"], s["median_first_close"]) == (3, 1, 2, 2.0, 35.0)
    assert (s["grasp_rate"], s["lift_rate"], s["other_object_rate"]) == (2 / 3, 1 / 3, 1 / 3)
    assert s["successes_per_task"] == {"t/0": 1, "t/1": 0} and s["nearest_named_rate"] == 0.5  # of the 2 that closed
    assert libero_probe.summarise(rows[2:])["nearest_named_rate"] is None  # none closed
    assert (s["picked"], s["picked_named_rate"]) == (2, 0.5)  # of the 2 that ended with an object: "a" was named
    assert libero_probe.summarise(rows[2:])["picked_named_rate"] is None
    (tmp_path / "file").write_text("a file where --out wants a folder")
    for argv, words in ((["--model", "/nonexistent"], "no checkpoint there"), (["--expert", "--states", "0,x"], "--states"),
                        (["--expert", "--states", "50"], "50 stored states"),
                        (["--expert", "--language", "paraphrase"], "--language"),
                        (["--expert", "--tasks", "libero_goal/0"], "LIBERO-Object tasks"),
                        (["--expert", "--language", "swap", "--tasks", "libero_object/11"], "LIBERO-Object tasks"),
                        (["--expert", "--out", str(tmp_path)], "is a folder"),
                        (["--expert", "--out", str(tmp_path / "file" / "probe.json")], "cannot write there")):
        with pytest.raises(SystemExit) as stop:
            libero_probe.main(argv)
        assert stop.value.code == 2 and words in capsys.readouterr().err


@pytest.mark.parametrize("argv,env,words", [([], {}, "usage:"), (["a=b"], {"LANGUAGE": "paraphrase"}, "use own or swap")])
def test_the_lever_script_refuses_a_bad_call_in_one_line_before_anything_loads(argv, env, words):
    import os
    import subprocess

    done = subprocess.run(["bash", str(REPO / "scripts" / "libero_levers.sh"), *argv], capture_output=True, text=True,
                          env={**os.environ, **env}, timeout=30)
    assert done.returncode == 2 and words in done.stderr and len(done.stderr.splitlines()) == 1


def test_the_lever_table_reads_probe_results_in_order_and_refuses_foreign_files(tmp_path, capsys):
    from reference_policies import libero_probe

    rows = [dict(task="t/0", target="a", first_close=30, reach_xy_cm=1.0, held_named=True, lifted_named=True,
                 success=True, picked="a"),
            dict(task="t/1", target="c", first_close=None, reach_xy_cm=None, held_named=False, lifted_named=False,
                 success=False, picked=None)]
    (tmp_path / "a.json").write_text(json.dumps({"summary": libero_probe.summarise(rows)}))
    (tmp_path / "b.json").write_text(json.dumps({"summary": libero_probe.summarise(rows[1:])}))
    assert libero_probe.main(["--table", f"second={tmp_path / 'a.json'}", f"first={tmp_path / 'b.json'}"]) == 0
    lines = capsys.readouterr().out.splitlines()
    # made before "nearest" and the stall: "-"
    assert lines[2] == "| second | 2 | 1/2 | 1.0 (1 closed) | 30 | - | 50% | 50% | 0% | 100% of 1 | - |"
    assert lines[3] == "| first | 1 | 0/1 | - | - | - | 0% | 0% | 0% | 0 picked | - |" and len(lines) == 4
    old = {k: v for k, v in libero_probe.summarise(rows).items() if k not in ("picked", "picked_named_rate")}
    (tmp_path / "old.json").write_text(json.dumps({"summary": old, "episodes": rows}))  # made before the last column
    assert libero_probe.main(["--table", f"old={tmp_path / 'old.json'}"]) == 0
    assert capsys.readouterr().out.splitlines()[2].endswith("| 0% | 100% of 1 | - |")  # summarised again from its rows
    (tmp_path / "rows.json").write_text(json.dumps({"summary": old, "episodes": [1, 2]}))
    (tmp_path / "torn.json").write_text('{"summary": {"episodes": 3')
    (tmp_path / "other.json").write_text('{"summary": [1, 2]}')
    big = tmp_path / "big.json"
    with open(big, "wb") as f:
        f.truncate(65 << 20)
    for spec, words in (("nolabel.json", "LABEL=FILE.json"), (f"x={tmp_path / 'torn.json'}", "not a probe result"),
                        (f"x={tmp_path / 'other.json'}", "not a probe result"), (f"x={big}", "under 64 MiB"),
                        (f"x={tmp_path / 'rows.json'}", "not a probe result"),
                        (f"x={tmp_path}", "not a probe result")):
        with pytest.raises(SystemExit) as stop:
            libero_probe.main(["--table", spec])
        assert stop.value.code == 2 and words in capsys.readouterr().err


def _stall_actions(stall: int, close_at: int = 10, steps: int = 280) -> np.ndarray:
    """Libero actions: approach open, close at `close_at` for 5 steps, then `stall` steps open and barely moving,
    then open and moving (|z| 0.9) to the end."""
    a = np.zeros((steps, 7))
    a[:, 2], a[:, 6] = -0.9, 1.0
    a[close_at:close_at + 5, 6] = 0.0
    a[close_at + 5:close_at + 5 + stall, :3] = [0.1, -0.29, 0.05]
    return a


def test_a_stall_is_the_longest_open_and_quiet_run_after_the_first_close_and_the_probe_tables_it(tmp_path, capsys):
    from reference_policies import libero_probe

    assert G.longest_stall(_stall_actions(120)) == (15, 120)
    assert G.longest_stall(_stall_actions(0)) == (0, 0)
    before = _stall_actions(0, close_at=60)
    before[:55, :3] = 0.0  # quiet and open before the first close: approaching, not stalling
    assert G.longest_stall(before) == (0, 0)
    never = _stall_actions(0)
    never[:, 6] = 1.0
    never[:, :3] = 0.0
    assert G.longest_stall(never) == (0, 0)  # never closed
    closed = _stall_actions(120)
    closed[60, 6] = 0.2  # one close in the middle splits it: the longest part counts
    assert G.longest_stall(closed) == (61, 74)
    loud = _stall_actions(120)
    loud[40:, 1] = -0.3  # at the threshold: moving
    assert G.longest_stall(loud) == (15, 25)
    # where the hand was at the stall's middle step, from the named object's box (centre (0, 0), top 0.10 m)
    actions = _stall_actions(100, steps=130)
    # the demonstrator's label after each step: open, but closing at step 65 only (the stall's middle)
    labels = [np.array([0, 0, 0, 0, 0, 0, 0.0 if k == 65 else 1.0]) for k in range(130)]
    where = [(np.array([0.03, 0.04, 0.10 + 0.001 * k]), np.array([-0.02, -0.02, 0.0]), np.array([0.02, 0.02, 0.10]),
              labels[k]) for k in range(130)]
    m = libero_probe.stall_measures(list(actions), where)
    assert m == {"stall_steps": 100, "stall_xy_cm": 5.0, "stall_above_top_cm": pytest.approx(6.5),  # step 15 + 50
                 "stall_expert_closes": True}
    assert libero_probe.stall_measures(list(_stall_actions(0)), where * 3)["stall_xy_cm"] is None
    stalls = ((150, 2.0, 1.0, True), (100, 4.0, 3.0, False), (99, 9.0, 9.0, True), (0, None, None, None))
    rows = [dict(task="t/0", target="a", first_close=10, reach_xy_cm=1.0, held_named=False, lifted_named=False,
                 success=False, picked=None, stall_steps=s, stall_xy_cm=xy, stall_above_top_cm=z, stall_expert_closes=c)
            for s, xy, z, c in stalls]
    s = libero_probe.summarise(rows)
    assert (s["stalled"], s["stall_rate"]) == (2, 0.5)
    assert (s["median_stall_xy_cm"], s["median_stall_above_top_cm"]) == (3.0, 2.0)
    assert s["stalled_expert_closes"] == 1  # of the two stalls of 100+ steps
    assert libero_probe.summarise(rows[2:])["stalled"] == 0
    unmeasured = {k: v for k, v in rows[1].items() if k != "stall_steps"}  # a row from before the stall
    assert libero_probe.summarise([{**rows[0], "stall_steps": 0}, unmeasured])["stalled"] is None
    (tmp_path / "p.json").write_text(json.dumps({"summary": s}))
    assert libero_probe.main(["--table", f"p={tmp_path / 'p.json'}"]) == 0
    assert capsys.readouterr().out.splitlines()[2].endswith(
        "| 50% (hand 3.0 cm off the object, 2.0 cm above its top; the demonstrator would close in 1 of 2) |")


def _libero_run(folder, episodes: dict, action_space: str = "libero"):
    """A LIBERO run folder by hand (rows without digests: read unverified): {task: [(success, actions)]}."""
    from tests.analysis.test_compare_outcomes import PROTOCOL, write_run

    protocol = {**PROTOCOL, "env": {**PROTOCOL["env"], "action_space": action_space}}
    write_run(folder, {t: [ok for ok, _ in eps] for t, eps in episodes.items()}, protocol=protocol)
    rows = [json.loads(line) for line in (folder / "results.jsonl").read_text().splitlines()]
    for row in rows:  # the steps each row records are its actions' (the store checks them)
        row["steps"] = len(episodes[row["task"]][row["episode"]][1])
    (folder / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    for task, eps in episodes.items():
        for k, (_, actions) in enumerate(eps):
            (folder / task / f"episode_{k}").mkdir(parents=True)
            np.savez(folder / task / f"episode_{k}" / "actions.npz", executed=actions)
            np.savez(folder / task / f"episode_{k}" / "attention.npz", steps=np.arange(len(actions)))
    return folder


def test_stalls_of_a_run_folder_count_its_failed_episodes_and_other_runs_are_one_line(tmp_path, capsys):
    from reference_policies import libero_probe

    run = _libero_run(tmp_path / "run", {
        "libero_object/0": [(False, _stall_actions(130)), (False, _stall_actions(99)), (True, _stall_actions(200))],
        "libero_object/8": [(False, _stall_actions(100))]})
    assert libero_probe.run_stalls(run) == [("libero_object/0", 3, 2, 1), ("libero_object/8", 1, 1, 1)]
    assert libero_probe.main(["--stalls", str(run)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[2] == "| libero_object/0 | 3 | 2 | 1 |" and out[-1] == "| all | 4 | 3 | 2 |"
    other = _libero_run(tmp_path / "robosuite", {"Lift": [(False, _stall_actions(130))]}, action_space="octo-delta")
    torn = _libero_run(tmp_path / "torn", {"libero_object/0": [(False, _stall_actions(130))]})
    (torn / "libero_object/0/episode_0/actions.npz").write_bytes(b"PK\x03\x04 not a zip")
    wide = _libero_run(tmp_path / "wide", {"libero_object/0": [(False, np.zeros((280, 9)))]})
    for folder, words in ((other, "not a run in the libero action space"), (torn, "actions.npz"),
                          (wide, "not steps x 7"), (tmp_path / "none", "does not exist"),
                          (tmp_path, "pass one of them")):
        with pytest.raises(SystemExit) as stop:
            libero_probe.main(["--stalls", str(folder)])
        err = capsys.readouterr().err
        assert stop.value.code == 2 and words in err and "Traceback" not in err


def test_a_probe_result_is_reused_only_for_the_same_checkpoint_states_tasks_and_limit(tmp_path, capsys):
    from reference_policies import libero_probe

    rows = [dict(task="libero_object/0", target="a", first_close=30, reach_xy_cm=1.0, held_named=True,
                 lifted_named=True, success=True, picked="a")]
    key = libero_probe.probe_key(None, [0], ("libero_object/0",), 280)
    out = tmp_path / "expert.json"
    out.write_text(json.dumps({"key": key, "summary": libero_probe.summarise(rows), "episodes": rows}))
    before = out.read_bytes()
    # the same inputs: reused at once (no simulator starts), the file untouched
    assert libero_probe.main(["--expert", "--states", "0", "--tasks", "libero_object/0", "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["successes"] == 1 and out.read_bytes() == before
    assert libero_probe._finished(str(out), key) is not None
    for other in (libero_probe.probe_key(None, [0, 1], ("libero_object/0",), 280),
                  libero_probe.probe_key(None, [0], ("libero_object/1",), 280),
                  libero_probe.probe_key(None, [0], ("libero_object/0",), 100),
                  libero_probe.probe_key(None, [0], ("libero_object/0",), 280, language="swap"),
                  libero_probe.probe_key(MODEL, [0], ("libero_object/0",), 280)):
        assert libero_probe._finished(str(out), other) is None
    out.write_text(out.read_text()[:50])  # torn
    assert libero_probe._finished(str(out), key) is None
    with open(out, "wb") as f:
        f.truncate(65 << 20)  # huge
    assert libero_probe._finished(str(out), key) is None
    edited = tmp_path / "model"
    edited.mkdir()
    for name in ("config.json", "dataset_statistics.json", "harness.toml"):
        (edited / name).write_bytes((MODEL / name).read_bytes())
    fingerprint = libero_probe.probe_key(str(edited), [0], ("libero_object/0",), 280)["checkpoint"]
    (edited / "harness.toml").write_text((MODEL / "harness.toml").read_text() + "\n# edited\n")
    assert libero_probe.probe_key(str(edited), [0], ("libero_object/0",), 280)["checkpoint"] != fingerprint


@pytest.mark.slow
def test_the_grasp_probe_measures_the_expert_as_a_yardstick_and_runs_the_committed_policy():
    """Known answer: the state-based expert closes centred on the named object, holds and lifts it, and succeeds;
    so does the committed reference on the second demo's episode."""
    _needs_libero()
    from reference_policies import libero_probe

    expert = libero_probe.probe(None, [0], ("libero_object/0",), workers=1)
    json.dumps(expert)  # what --out writes: plain JSON types only (numpy's bool_ once lost a 20-minute probe)
    (row,) = expert["episodes"]
    assert row["success"] and row["held_named"] and row["lifted_named"] and row["picked"] == row["target"]
    assert row["nearest_at_close"] == row["target"] and expert["summary"]["nearest_named_rate"] == 1.0
    assert row["reach_xy_cm"] < 1.0 and abs(row["reach_z_cm"]) < 1.5 and 10 < row["first_close"] < row["steps"]
    assert row["stall_steps"] < 20 and expert["summary"]["stalled"] == 0  # it closes, lifts and places: no waiting
    # told the swap (scene /0 hears /1's instruction): the expert picks the cream cheese, which alone ends in the
    # basket, so the swap succeeds though the scene's own predicate (the alphabet soup) never holds
    swapped = libero_probe.probe(None, [0], ("libero_object/0",), workers=1, language="swap")
    (row,) = swapped["episodes"]
    assert row["instruction"] == libero_tasks.get_libero_task("libero_object/1").instruction
    assert row["target"] == row["picked"] == "cream_cheese_1" and row["success"] and row["steps"] < 280
    assert swapped["summary"]["picked_named_rate"] == 1.0 and swapped["language"] == "swap"
    # the reference, as evaluated (its conventions), on the second demo's episode (scripts/demo_libero.sh:
    # libero_object/2, state 0): it picks the salad dressing and places it in the basket
    policy = libero_probe.probe(str(MODEL), [0], ("libero_object/2",), workers=1, max_steps=150)
    (row,) = policy["episodes"]
    assert policy["model"] == str(MODEL) and row["success"] and row["steps"] < 150
    assert row["held_named"] and row["lifted_named"] and row["picked"] == row["target"] == "salad_dressing_1"
    assert row["nearest_at_close"] == row["target"] and row["reach_xy_cm"] < 3.0


@pytest.mark.slow
def test_sampled_placements_repeat_per_seed_and_are_none_of_the_stored_evaluation_states(camera_free_env):
    env = camera_free_env
    env.reset(seed=1_000_000, options={"initial_state": "sampled", "settle_steps": 0})
    first = env.sim_state()
    env.reset(seed=3)  # a stored state in between
    env.reset(seed=1_000_000, options={"initial_state": "sampled", "settle_steps": 0})
    np.testing.assert_array_equal(env.sim_state(), first)
    env.reset(seed=1_000_001, options={"initial_state": "sampled", "settle_steps": 0})
    assert not np.allclose(env.sim_state(), first)
    stored = np.stack([env.initial_state(k) for k in range(50)])
    assert stored.shape[1] == first.shape[0]
    # objects' free joints differ from every stored state by more than settling noise (1 mm)
    assert np.min(np.max(np.abs(stored[:, 1:] - first[None, 1:]), axis=1)) > 1e-3


@pytest.mark.slow
def test_the_outcome_names_the_object_in_the_basket_or_none(camera_free_env):
    env = camera_free_env
    env.reset(seed=0)
    outcome = env.episode_outcome()
    assert (outcome["picked_object"], outcome["placed"], outcome["held"]) == (None, [], [])
    assert "alphabet_soup_1" in outcome["objects"] and "basket_1" not in outcome["objects"]
    basket = env.object_poses()["basket_1"]
    centre = (basket["low"] + basket["high"]) / 2
    env.place_object("cream_cheese_1", [centre[0], centre[1], basket["low"][2] + 0.06])
    for _ in range(15):
        env.step(np.array([0, 0, 0, 0, 0, 0, 1.0], np.float32))
    outcome = env.episode_outcome()
    assert outcome["picked_object"] == "cream_cheese_1" and outcome["placed"] == ["cream_cheese_1"]


@pytest.mark.slow
class TestTheRecorderInSceneSix:
    """Scene /6 (the butter) as the recorder makes it: one env for both tests, closed after them (a LIBERO server
    with two 128 px cameras holds about 2 GB)."""

    @pytest.fixture(scope="class")
    def butter_demo_env(self):
        _needs_libero()
        from reference_policies.libero_demos import LiberoDemoConfig, make_env

        env = make_env("libero_object/6", LiberoDemoConfig())
        yield env
        env.close()

    @staticmethod
    def _missing(config):
        """`config` with `--missed-grasps 1`: every episode starts with a missed grasp."""
        from dataclasses import replace

        from reference_policies.libero_demos import MissConfig

        return replace(config, bursts=replace(config.bursts, miss=MissConfig(rate=1.0)))

    @staticmethod
    def _closes(gripper) -> int:
        """How often the gripper labels close (0 after 1)."""
        return int(np.count_nonzero(np.diff((gripper == 0).astype(int)) == 1))

    def test_a_demonstration_from_a_sampled_placement_is_recorded_as_the_policy_sees_it(self, butter_demo_env):
        """Through record_episode with `--missed-grasps 1` (MissConfig rate 1: the miss, then the bursts), the expert
        still succeeds; the episode holds the frames the policy sees and the expert's labels (close, reopen, close).
        record_episode without a miss runs in the swapped-instruction test below."""
        from reference_policies.libero_demos import LiberoDemoConfig, record_episode

        config = LiberoDemoConfig()
        episode = record_episode(butter_demo_env, "butter_1", config.task_seed_base("libero_object/6") + 1,
                                 self._missing(config))
        assert episode is not None  # the expert succeeds under the recording noise and the missed grasp
        n = len(episode["action"])
        assert 50 < n < config.max_steps
        assert episode["image_primary"].shape == (n, 128, 128, 3) and episode["image_wrist"].shape == (n, 128, 128, 3)
        assert episode["proprio"].shape == (n, 8)
        gripper = episode["action"][:, 6]
        assert set(np.unique(gripper)) == {0.0, 1.0}  # the libero gripper: 1 open, 0 closed
        assert self._closes(gripper) >= 2  # the labels: close, reopen, close
        assert np.abs(episode["action"][:, :6]).max() <= 1.0

    def test_a_missed_grasp_closes_beside_the_object_where_the_policy_stalls_and_the_expert_recovers(self,
                                                                                                     butter_demo_env):
        """MissConfig's perturbation in the real scene /6 (the butter): the hand closes 3 cm off the object's centre,
        below its top (where the reference stalls: docs/libero-reference.md), and the expert, taking over, still places
        the butter; the labels are the expert's own (they close, reopen and close again). The test above records one
        through record_episode."""
        from reference_policies.demos import noisy_episode
        from reference_policies.libero_demos import LiberoDemoConfig, MissedGrasp
        from reference_policies.libero_expert import LiberoObjectLabeller

        config = LiberoDemoConfig()
        missing = self._missing(config)
        seed = config.task_seed_base("libero_object/6")
        env = butter_demo_env
        rng = np.random.default_rng(seed)
        obs, _ = env.reset(seed=seed, options={"initial_state": "sampled"})
        expert = LiberoObjectLabeller("butter_1", config=config.expert)
        miss = MissedGrasp(missing.bursts.miss, env, "butter_1", config.expert, rng)
        assert miss.active and 6 <= miss.close_steps <= 10
        episode = noisy_episode(env, obs, lambda o: expert.act(env, miss.see(o)), {"image_primary": 32}, config.noise,
                                rng, config.max_steps, miss)
        assert episode is not None and not miss.active and len(miss.closes) == miss.close_steps
        off, above = np.array(miss.closes).T
        assert np.all((off > 0.02) & (off < 0.04)) and np.all(above < 0.0)  # beside it, below its top
        assert self._closes(episode["action"][:, 6]) >= 2  # the labels: close, reopen, close


@pytest.mark.slow
def test_a_swapped_instruction_demonstration_picks_the_named_object_in_another_tasks_scene(tmp_path):
    """Recorded through the pipeline's recorder with `swaps=True`: in scene /6 (the butter) the expert picks the
    object of swap_candidates' entry `seed mod 5`, each frame stores that task's index, and the seed is in the
    task's swap block (never the own demonstrations' seeds)."""
    _needs_libero()
    from reference_policies.libero_demos import (LIBERO_OBJECT_TASKS, SWAP_SEED_OFFSET, LiberoDemoConfig, append_swaps,
                                                record_libero_demos, swap_candidates)
    from reference_policies.libero_eval import scene_objects

    config = LiberoDemoConfig(tasks=("libero_object/6",), episodes=1, jobs_per_task=1, swaps=True)
    summary = record_libero_demos(config, tmp_path, workers=1)
    assert summary["libero_object/6"]["episodes"] == 1
    with np.load(tmp_path / "libero_object_6.npz") as data:
        seed, named, n = int(data["seeds"][0]), data["named"], len(data["action"])
    assert seed == config.task_seed_base("libero_object/6") == 1_060_000 + SWAP_SEED_OFFSET + 0  # the first try held
    expected = swap_candidates("libero_object/6", scene_objects("libero_object/6"))[seed % 5]
    assert expected != "libero_object/6" and set(named.tolist()) == {LIBERO_OBJECT_TASKS.index(expected)}
    base = {t: {"action": np.zeros((2, 7), np.float32), "episode": np.array([0, 1], np.int32),
                "step": np.zeros(2, np.int32), "seeds": np.array([7, 8]), "lengths": np.array([1, 1], np.int32),
                "image_primary": np.zeros((2, 128, 128, 3), np.uint8), "image_wrist": np.zeros((2, 128, 128, 3), np.uint8),
                "proprio": np.zeros((2, 8), np.float32)} for t in ("libero_object/6", expected)}
    merged = append_swaps(base, tmp_path, ("libero_object/6",))
    assert len(merged[expected]["action"]) == 2 + n and merged[expected]["episode"][2:].tolist() == [2] * n
    assert len(merged["libero_object/6"]["action"]) == 2  # the scene's own task gains nothing


@pytest.mark.slow
def test_the_labeller_recovers_from_a_grasp_closed_beside_the_object(camera_free_env):
    """The policy's commonest failure, set up by hand: the hand 4 cm beside the object at grasp height, fingers
    closed on nothing. From there the state-based labeller (acting alone) opens, backs up, re-grasps and puts the
    object in the basket: LIBERO's own success predicate.
    In the module's camera-free libero_object/0 env (one LIBERO server fewer): the recorder's make_env with no
    cameras is the same env (the libero action space, the suite's 280-step limit; without a camera the image
    convention and fast render change nothing), and a sampled reset places every object and zeroes the gripper
    whatever ran before (tests/libero/test_libero_env.py), so the episode is the one a fresh env would run."""
    from reference_policies.libero_expert import OPEN, LiberoObjectLabeller

    env = camera_free_env
    obs, _ = env.reset(seed=7_000_000, options={"initial_state": "sampled"})
    lab = LiberoObjectLabeller("alphabet_soup_1")
    box = env.object_poses()["alphabet_soup_1"]
    beside = (box["low"] + box["high"]) / 2 + np.array([0.04, 0.0, 0.0])
    for _ in range(80):  # drive there open, then close on nothing
        hand = obs["proprio"][:3]
        arm = np.clip(10 * (beside - hand) / 0.05, -1, 1)
        obs, *_ = env.step(np.r_[arm, 0, 0, 0, 1.0].astype(np.float32))
    for _ in range(15):
        obs, *_ = env.step(np.array([0, 0, 0, 0, 0, 0, 0.0], np.float32))
    assert np.abs(obs["proprio"][6:8]).sum() < LiberoObjectLabeller.EMPTY_FINGERS
    assert not env.grasping("alphabet_soup_1")
    first = lab.act(env, obs)
    assert first[6] == OPEN and first[2] > 0  # open and back up
    success = False
    for _ in range(250):
        obs, _, _, _, info = env.step(lab.act(env, obs))
        if info["success"]:
            success = True
            break
    assert success


@pytest.mark.slow
def test_libero_dagger_labels_the_policys_own_states_and_appends_them(tmp_path, caplog):
    """A short collection with the committed policy: files per task in the demonstrations' layout, the seeds of its
    block, labels in the libero action space; reused only for the same configuration and checkpoint; appended as
    further episodes of each task."""
    _needs_libero()
    from reference_policies import libero_dagger

    config = libero_dagger.LiberoDaggerConfig(tasks=("libero_object/3",), episodes=2, max_steps=6)
    summary = libero_dagger.collect(MODEL, tmp_path / "c", config, workers=1)
    assert summary["libero_object/3"]["episodes"] == 2 and summary["libero_object/3"]["steps"] == 12
    with np.load(tmp_path / "c" / "libero_object_3.npz") as data:
        arrays = {k: data[k] for k in data.files}
    assert arrays["seeds"].tolist() == config.seeds("libero_object/3") == [2_030_000, 2_030_001]
    assert arrays["image_primary"].shape == (12, 128, 128, 3) and arrays["image_wrist"].shape == (12, 128, 128, 3)
    assert arrays["proprio"].shape == (12, 8) and arrays["success"].tolist() == [False, False]
    assert set(np.unique(arrays["action"][:, 6])) <= {0.0, 1.0} and np.abs(arrays["action"][:, :6]).max() <= 1.0
    assert libero_dagger.existing(config, MODEL, tmp_path / "c") is not None
    # a stop after the first job: only the second runs again, and the task's file holds the same arrays
    whole = arrays
    (tmp_path / "c" / "libero_object_3.npz").unlink()
    (tmp_path / "c" / "jobs" / "libero_object_3_2030001.npz").unlink()
    (tmp_path / "c" / "jobs" / "libero_object_3_2030000.npz").write_bytes(b"torn")
    (tmp_path / "c" / "summary.json").unlink()
    with caplog.at_level(logging.INFO, logger="reference_policies.libero_dagger"):
        libero_dagger.collect(MODEL, tmp_path / "c", config, workers=1)
    assert "seeds 2030000..: 1 episodes" in caplog.text and "seeds 2030001..: 1 episodes" in caplog.text
    caplog.clear()
    (tmp_path / "c" / "libero_object_3.npz").unlink()
    (tmp_path / "c" / "jobs" / "libero_object_3_2030001.npz").unlink()
    with caplog.at_level(logging.INFO):  # the reuse is logged by reference_policies.demos
        libero_dagger.collect(MODEL, tmp_path / "c", config, workers=1)
    assert "reusing 1 of 2" in caplog.text and "seeds 2030000..:" not in caplog.text
    with np.load(tmp_path / "c" / "libero_object_3.npz") as data:
        assert sorted(data.files) == sorted(whole) and all(np.array_equal(data[k], whole[k]) for k in whole)
    assert libero_dagger.existing(libero_dagger.LiberoDaggerConfig(tasks=config.tasks, episodes=4, max_steps=6),
                                  MODEL, tmp_path / "c") is None
    other = tmp_path / "other"
    other.mkdir()
    for name in ("config.json", "dataset_statistics.json"):
        (other / name).write_bytes((MODEL / name).read_bytes())
    (other / "dataset_statistics.json").write_text((MODEL / "dataset_statistics.json").read_text() + " ")
    assert libero_dagger.existing(config, other, tmp_path / "c") is None  # another checkpoint acted
    demos = {"libero_object/3": {k: v[:7] if k not in ("seeds", "lengths", "success") else v
                                 for k, v in arrays.items() if k != "success"}}
    demos["libero_object/3"]["episode"] = np.zeros(7, np.int32)
    merged = libero_dagger.append_all(demos, tmp_path / "c", config.tasks)["libero_object/3"]
    assert len(merged["action"]) == 7 + 12 and merged["episode"].max() == 2


@pytest.mark.slow
def test_the_pipeline_trains_libero_tasks_warm_started_from_the_robosuite_reference(tmp_path):
    """Two training steps on synthetic frames of two LIBERO-Object tasks, warm-started from the committed robosuite
    reference: every parameter copied except the frozen T5 word table (another vocabulary: kept fresh); the result
    loads as an Octo checkpoint with the LIBERO conventions, and its vocabulary holds the objects' words."""
    from dataclasses import replace

    from harness.octo import load_pretrained
    from reference_policies.libero_pipeline import DATASET_KEY, conventions_toml, instructions
    from reference_policies.train import TrainConfig, train

    rng = np.random.default_rng(0)
    tasks = ("libero_object/0", "libero_object/7")
    demos = {}
    for task in tasks:
        n = 9
        demos[task] = {"image_primary": rng.integers(0, 255, (n, 128, 128, 3), np.uint8),
                       "image_wrist": rng.integers(0, 255, (n, 64, 64, 3), np.uint8),
                       "proprio": rng.normal(size=(n, 8)).astype(np.float32),
                       "action": np.concatenate([rng.uniform(-1, 1, (n, 6)), rng.integers(0, 2, (n, 1))], 1).astype(np.float32),
                       "episode": np.repeat([0, 1], [5, 4]).astype(np.int32), "step": np.r_[0:5, 0:4].astype(np.int32),
                       "seeds": np.array([1, 2]), "lengths": np.array([5, 4], np.int32)}
    config = replace(TrainConfig(), steps=2, batch_size=4, log_every=1, checkpoint_every=2, warmup_steps=1,
                     task_weights=(), init_from=str(REPO / "models" / "octo-reference-robosuite"))
    summary = train(demos, tmp_path, config, instructions=instructions(tasks), dataset_key=DATASET_KEY,
                    conventions=conventions_toml(WRIST_64))
    assert [f.split()[0] for f in summary["warm_start"]["fresh"]] == [
        "octo_transformer/task_tokenizers_language/hf_model/shared/embedding"]
    assert summary["warm_start"]["copied"] > 100 and not summary["warm_start"]["resized"]
    model = load_pretrained(str(tmp_path))
    assert model.unnormalization_statistics(DATASET_KEY)["mask"].tolist() == [True] * 6 + [False]
    vocab = json.loads((tmp_path / "tokenizer" / "tokenizer.json").read_text())["model"]["vocab"]
    assert {"alphabet", "soup", "milk", "basket", "grab"} <= set(vocab) and "ketchup" not in vocab
    assert 'action_space = "libero"' in (tmp_path / "harness.toml").read_text()


@pytest.mark.slow
def test_a_dagger_round_trains_stage_1_collects_once_then_fine_tunes_on_demonstrations_and_corrections(tmp_path):
    """pipeline.dagger_round with a stand-in collection (the collection itself is tested on LIBERO above): stage 1
    is trained into <data>/stage1, the collector is handed that checkpoint, the fine-tuning sees the corrections'
    frames too, starts from stage 1 with seed + 1, and a second call reuses stage 1 and the corrections."""
    from dataclasses import replace

    from reference_policies.libero_pipeline import DATASET_KEY, conventions_toml, instructions
    from reference_policies.pipeline import dagger_round
    from reference_policies.train import TrainConfig

    rng = np.random.default_rng(1)
    task = "libero_object/2"

    def frames(n):
        return {"image_primary": rng.integers(0, 255, (n, 128, 128, 3), np.uint8),
                "image_wrist": rng.integers(0, 255, (n, 64, 64, 3), np.uint8),
                "proprio": rng.normal(size=(n, 8)).astype(np.float32),
                "action": rng.uniform(-1, 1, (n, 7)).astype(np.float32),
                "episode": np.zeros(n, np.int32), "step": np.arange(n, dtype=np.int32),
                "seeds": np.array([1]), "lengths": np.array([n], np.int32)}

    demos = {task: frames(6)}
    corrections = frames(5)
    collected = []

    def collect(model, out):
        collected.append(Path(model))
        return {"seconds": 2.0}

    def existing(model, out):
        return {"seconds": 2.0} if collected else None

    def append(d, out):
        merged = {k: np.concatenate([d[task][k], corrections[k]]) for k in d[task]}
        return {task: merged}

    # the rounds' bookkeeping, not the model, is under test: a one-layer, 32-wide network (5 trainings of the full
    # reference network were 130 s of CI's time); every training here is one XLA program, compiled once (about 30 s
    # under load): the schedule's rate and the T5 encodings are arguments of the step, not constants of it
    config = replace(TrainConfig(), steps=2, batch_size=4, log_every=1, checkpoint_every=2, warmup_steps=1,
                     learning_rate=1e-4,
                     task_weights=(), init_from=None, width=32, layers=1, heads=2, mlp_dim=64,
                     stem_features=(32, 32, 32, 32), head_hidden=32, t5_width=16)
    kwargs = {"instructions": instructions((task,)), "dataset_key": DATASET_KEY, "conventions": conventions_toml(WRIST_64)}
    result = dagger_round(demos, config, tmp_path / "data", tmp_path / "out", collect=collect, existing=existing,
                          append=append, steps=2, learning_rate=1e-4, what="test", train_kwargs=kwargs)
    assert collected == [tmp_path / "data" / "stage1"]
    assert (tmp_path / "data" / "stage1" / "2" / "default" / "checkpoint").is_file()
    assert result["frames"] == 11 and result["stage1"]["frames"] == 6
    assert result["config"]["seed"] == config.seed + 1 and result["config"]["init_from"] == str(tmp_path / "data" / "stage1")
    assert result["dagger"] == {"seconds": 2.0} and (tmp_path / "out" / "harness.toml").is_file()
    again = dagger_round(demos, config, tmp_path / "data", tmp_path / "out2", collect=collect, existing=existing,
                         append=append, steps=2, learning_rate=1e-4, what="test", train_kwargs=kwargs)
    assert len(collected) == 1 and again["frames"] == 11  # stage 1 and the corrections reused

    # two rounds: round 2's collector acts with round 1's checkpoint; its corrections weigh more near the grasp
    from reference_policies.pipeline import dagger_rounds

    acted = []

    def collect_round(model, out, r):
        acted.append((r, Path(model), Path(out).name))
        return {"seconds": 1.0}

    def append_weighted(d, out):
        extra = {**corrections, "weight": np.full(5, 3.0)}
        base = {**d[task], "weight": d[task].get("weight", np.ones(len(d[task]["action"])))}
        return {task: {k: np.concatenate([base[k], extra[k]]) for k in base}}

    two = dagger_rounds(demos, config, tmp_path / "data", tmp_path / "out3", rounds=2, collect=collect_round,
                        existing=lambda model, out, r: None, append=append_weighted, steps=2, learning_rate=1e-4,
                        what="test", train_kwargs=kwargs)
    # stage 1 reused from above; round 1's checkpoint acts in round 2
    assert acted == [(1, tmp_path / "data" / "stage1", "dagger"), (2, tmp_path / "data" / "round1", "dagger2")]
    assert (tmp_path / "data" / "round1" / "2" / "default" / "checkpoint").is_file()
    # retrain: the round trains as stage 1 did (its steps, learning rate and warm start, seed + 1), not from the
    # checkpoint that acted (data2/stage1), warm-started from the first stage 1
    warm = str(tmp_path / "data" / "stage1")
    anew = dagger_rounds(demos, replace(config, steps=3, init_from=warm), tmp_path / "data2", tmp_path / "out4",
                         rounds=1, collect=collect_round, existing=lambda model, out, r: None, append=append, steps=2,
                         learning_rate=1e-4, what="test", train_kwargs=kwargs, retrain=True)
    assert anew["config"] == {**anew["stage1"]["config"], "seed": config.seed + 1} and anew["frames"] == 11
    assert anew["config"]["steps"] == 3 and anew["config"]["init_from"] == warm
    assert (tmp_path / "out4" / "3" / "default" / "checkpoint").is_file()
    assert two["frames"] == 16 and two["config"]["seed"] == config.seed + 2
    assert two["config"]["init_from"] == str(tmp_path / "data" / "round1") and len(two["rounds"]) == 2


# ------------------------------------------------------------------------------------------------ the committed policy


@pytest.mark.slow
def test_the_committed_policy_runs_libero_object_and_the_report_shows_its_grounding(tmp_path):
    """A short closed-loop episode of the committed policy on libero_object/0 (its harness.toml conventions, masks
    on) and one told task 7's instruction: episode.json carries the outcome, attention.npz the per-object measures,
    and `octo-harness report` renders a Grounding section in Chromium whose numbers are in tables/grounding_*.csv."""
    import csv
    import io

    from harness import cli
    from tests.helpers import browser as _browser

    _needs_libero()
    common = ["--model", str(MODEL), "--episodes", "1", "--seed", "0", "--max-steps", "6", "--fast-render",
              "--png-every", "0", "--no-video", "--out", str(tmp_path / "runs")]
    assert cli.main(["run", "--task", "libero_object/0", "--run-name", "own", *common]) == 0
    milk = envs.get_task("libero_object/7").instruction
    assert cli.main(["run", "--task", "libero_object/0", "--run-name", "swap", "--instruction", milk, "--no-masks",
                     *common]) == 0
    episode = tmp_path / "runs" / "own" / "libero_object" / "0" / "episode_0"
    meta = json.loads((episode / "episode.json").read_text())
    assert set(meta["outcome"]) == {"picked_object", "placed", "held", "objects"}
    assert "alphabet_soup_1" in meta["outcome"]["objects"] and "milk_1" in meta["outcome"]["objects"]
    with np.load(episode / "attention.npz") as z:
        assert z["measures/layer/mask_mass/image_primary/object.alphabet_soup_1"].shape == (6, 4)
        assert z["tokens/image_grids"].tolist() == [[8, 8], [8, 8]]  # both cameras as 8x8 patches (the wrist at 128 px)
        assert np.isfinite(z["metrics/share/wrist"]).all() and z["metrics/share/wrist"].shape == (6, 4)
    report = tmp_path / "report"
    assert cli.main(["report", str(tmp_path / "runs" / "own"), str(tmp_path / "runs" / "swap"), "--out", str(report)]) == 0
    lift = list(csv.DictReader(io.StringIO((report / "tables" / "grounding_lift.csv").read_text())))
    assert [(r["task"], r["camera"], r["layer"]) for r in lift if r["camera"] == "image_primary"] == [
        ("libero_object/0", "image_primary", str(layer)) for layer in range(4)]
    swaps = {r["run"]: r for r in csv.DictReader(io.StringIO((report / "tables" / "grounding_swap.csv").read_text()))}
    assert swaps["own"]["kind"] == "own" and swaps["swap"]["kind"] == "swap" and swaps["swap"]["blind_episodes"] == "1"
    dom = _browser(report / "report.html", tmp_path, "--dump-dom", "--virtual-time-budget=10000").stdout
    assert ">Grounding</h" in dom and 'href="#grounding"' in dom and "Named object vs the others" in dom
    # the EVAL.md command (scripts/evaluate_libero_reference.sh) over the same runs: written and printed once
    from harness.report.grounding import main as grounding_main

    eval_md = tmp_path / "EVAL.md"
    eval_md.write_text("# model: evaluation\n")
    assert grounding_main([str(tmp_path / "runs" / "own"), str(tmp_path / "runs" / "swap"), "--eval-md", str(eval_md)]) == 0
    text = eval_md.read_text()
    assert text.count("## Language grounding") == 1 and "| libero_object/0 |" in text
    assert (tmp_path / "figures" / "language-grounding.json").is_file()  # rendered from it (tests/docs/test_eval_sections.py)


@pytest.mark.slow
def test_a_grounding_section_of_runs_without_libero_object_episodes_is_refused_in_one_line(tmp_path, capsys):
    from harness.report import grounding

    with pytest.raises(ValueError, match="no run here holds LIBERO-Object episodes"):
        grounding.markdown([])
    # the command: one line, EVAL.md untouched (any run folder that holds no LIBERO-Object episode: a copy of the
    # committed robosuite baseline, its Lift episodes)
    import shutil

    run = tmp_path / "run"
    shutil.copytree(REPO / "results" / "baselines" / "reference-lift", run)
    eval_md = tmp_path / "EVAL.md"
    eval_md.write_text("# model: evaluation\n")
    capsys.readouterr()
    assert grounding.main([str(run), "--eval-md", str(eval_md)]) == 2
    assert eval_md.read_text() == "# model: evaluation\n" and capsys.readouterr().err.count("\n") == 1


def test_an_eval_md_section_is_replaced_in_place_or_appended_and_the_others_stay(tmp_path):
    from harness.files import replace_markdown_section

    path = tmp_path / "EVAL.md"
    path.write_text("# model: evaluation\n\ntable\n\n## Language grounding\n\nold\n\n## Robustness\n\nkept\n")
    replace_markdown_section(path, "## Language grounding", "## Language grounding\n\nnew\n")
    assert path.read_text() == "# model: evaluation\n\ntable\n\n## Language grounding\n\nnew\n\n## Robustness\n\nkept\n"
    replace_markdown_section(path, "## Closed loop", "## Closed loop\n\npairs\n")
    assert path.read_text().endswith("## Robustness\n\nkept\n\n## Closed loop\n\npairs\n")
    assert not list(tmp_path.glob("*.tmp.*"))  # written whole, no temporary left


@pytest.mark.parametrize("model", [MODEL, FIRST], ids=["reference", "first"])
def test_the_committed_policy_is_small_and_states_its_libero_conventions(model):
    total = sum(p.stat().st_size for p in model.rglob("*") if p.is_file())
    assert total <= 25 * 2**20  # the limit for a committed model folder
    from harness.conventions import CheckpointConventions
    from reference_policies.libero_pipeline import DATASET_KEY

    conventions = CheckpointConventions.read(model)
    assert conventions.env_options().action_space == "libero" and conventions.policy_config().dataset_key == DATASET_KEY
    summary = json.loads((model / "training_summary.json").read_text())
    demos = summary["demonstrations"]
    # every demonstration came from a sampled placement of the training seed block, never a stored state index
    assert all(demos[f"libero_object/{i}"]["seed_min"] >= 1_000_000 for i in range(10))


def test_the_reference_states_the_second_recipes_cameras_and_was_trained_on_its_demonstrations():
    """The reference reads both cameras at 128 px, as its demonstrations were recorded (the pipeline's harness.toml
    for the second recipe, byte for byte), its summary names the second recipe's demonstrator and count, and it was
    trained with the one command's defaults (steps, warm start), so `--out` alone rebuilds it."""
    from reference_policies.libero_demos import LIBERO_CAMERAS
    from reference_policies.libero_pipeline import DEFAULT_INIT, RECIPE_STEPS, RECIPES, conventions_toml

    assert (MODEL / "harness.toml").read_text() == conventions_toml(LIBERO_CAMERAS)
    assert dict((k, s) for k, _, s in LIBERO_CAMERAS) == {"image_primary": 128, "image_wrist": 128}
    summary = json.loads((MODEL / "training_summary.json").read_text())
    recorded = summary["demonstrations"]["config"]
    assert recorded["demonstrator"] == RECIPES["second"].demonstrator == "state"
    assert recorded["episodes"] == 50 and recorded["bursts"] is not None
    assert all(summary["demonstrations"][f"libero_object/{i}"]["episodes"] == 50 for i in range(10))
    assert summary["config"]["image_sizes"] == [["image_primary", 128], ["image_wrist", 128]]
    assert (summary["config"]["steps"], summary["config"]["init_from"]) == (RECIPE_STEPS["second"], DEFAULT_INIT)
    assert sorted(p.name for p in MODEL.iterdir() if p.name.isdigit()) == [str(RECIPE_STEPS["second"])]


def _legacy_run(folder: Path, intervention: str, outcomes: dict[tuple[str, int], bool]) -> Path:
    folder.mkdir(parents=True)
    tasks = sorted({t for t, _ in outcomes})
    manifest = {"tasks": tasks, "episodes": 2, "seed": 0, "protocol": {"policy": {"intervention": intervention}}}
    episodes = [{"task": t, "episode": k, "seed": k, "status": "ok", "success": ok, "steps": 5}
                for (t, k), ok in sorted(outcomes.items())]
    (folder / "results.json").write_text(json.dumps({"manifest": manifest, "episodes": episodes}))
    return folder


def test_the_closed_loop_section_is_written_when_the_script_names_its_command(tmp_path, capsys):
    """Known answer: paired by (task, state), 3 of 4 pairs succeed with mask-random and 1 with mask-top, both
    discordant pairs going one way (McNemar exact p = 0.5). The evaluation script passes --command, which once
    collided with the sub-command's name, so the section was never written and the exit code still said 0."""
    from reference_policies import libero_eval

    a, b = "libero_object/1", "libero_object/2"
    random_run = _legacy_run(tmp_path / "mask_random", "mask-random:8",
                             {(a, 0): True, (a, 1): True, (b, 0): True, (b, 1): False})
    top_run = _legacy_run(tmp_path / "mask_top", "mask-top:8:attention:3",
                          {(a, 0): True, (a, 1): False, (b, 0): False, (b, 1): False})
    eval_md = tmp_path / "EVAL.md"
    eval_md.write_text("# model: evaluation\n\n## Language grounding\n\nkept\n")
    assert libero_eval.main(["closed-loop", str(random_run), str(top_run), "--eval-md", str(eval_md),
                             "--command", "bash scripts/evaluate_libero_reference.sh 20 2", "--note", "n"]) == 0
    text = eval_md.read_text()
    assert text.count(libero_eval.CLOSED_LOOP) == 1 and "## Language grounding\n\nkept" in text
    assert "command `bash scripts/evaluate_libero_reference.sh 20 2`" in text
    assert "| **all tasks** | 4 | 3/4 [0.30, 0.95] | 1/4 [0.05, 0.70] | 2 | 0 | 0.5 |" in text
    assert f"| {a} | 2 | 2/2" in text and f"| {b} | 2 | 1/2" in text
    from harness.report import figures_file  # the section is what its figures file beside EVAL.md renders

    doc = figures_file.read(figures_file.path_for(eval_md, libero_eval.CLOSED_LOOP))
    assert figures_file.render(doc) in text and doc["section"] == libero_eval.CLOSED_LOOP
    (table,) = [b["table"] for b in doc["blocks"] if "table" in b]
    assert table["rows"][-1] == ["**all tasks**", "4", "3/4 [0.30, 0.95]", "1/4 [0.05, 0.70]", "2", "0", "0.5"]
    capsys.readouterr()
    assert libero_eval.main(["nonsense"]) == 0 and capsys.readouterr().out.strip() == libero_eval.NONSENSE

"""Controlled perturbations (issue 27): parsing and protocol recording, then known answers on the real simulator.

Known answers: level 0 is the nominal scene bit for bit (frames and protocol hash); the same (seed, level) gives the
same frames twice and in a fresh env; a camera shift moves the target's rendered centroid by the pixels the pinhole
model predicts from the drawn pose; distractor masks are non-empty and never touch the target; lighting levels darken
the frame monotonically (the stated direction); noise changes what the policy is fed, not the rendered scene or the
masks; a paraphrase changes the instruction the env reports; a texture change leaves the target's pixels untouched.
"""

from __future__ import annotations

import numpy as np
import pytest

import envs
from envs import perturbations as P
from envs.camera import project_points
from harness.run.protocol import Protocol, diff
from harness.run.settings import build_protocol, read_protocol_file


# ------------------------------------------------------------------------------------------- data

def test_parse_is_canonical_and_drops_level_zero():
    parsed = P.parse_perturb("lighting:2, camera:3,noise@image_wrist:1,texture:0")
    assert [p.label for p in parsed] == ["camera@image_primary:3", "lighting:2", "noise@image_wrist:1"]
    assert P.parse_perturb("camera:0,lighting:0") == ()
    assert P.perturb_text(P.parse_perturb(["camera:1", "language:5"])) == "camera@image_primary:1,language:5"


@pytest.mark.parametrize("text, fragment", [
    ("blur:2", "unknown kind"), ("camera:6", "level must be 0"), ("lighting@image_primary:1", "only camera and noise"),
    ("camera:1,camera@image_primary:2", "given twice"), ("camera", "expected KIND"), ("noise:1,noise@image_wrist:2", "twice"),
])
def test_parse_errors_are_one_line_naming_the_fix(text, fragment):
    with pytest.raises(P.PerturbationError) as err:
        P.parse_perturb(text)
    assert fragment in str(err.value) and "\n" not in str(err.value)


def test_protocol_records_perturb_only_when_set():
    plain = Protocol(model="random:octo-small-1.5", tasks=("Lift",))
    zero = plain.replace(perturb="camera:0,lighting:0")
    assert zero.perturb is None and zero.hash() == plain.hash() and "perturb" not in plain.to_dict()
    shifted = plain.replace(perturb="lighting:1,camera:2")
    assert shifted.to_dict()["perturb"] == "camera@image_primary:2,lighting:1"
    assert shifted.hash() != plain.hash() and diff(plain.to_dict(), shifted.to_dict()) == ["perturb"]
    assert Protocol.from_dict(shifted.to_dict()).hash() == shifted.hash()


def test_protocol_file_and_flags_take_perturb(tmp_path):
    path = tmp_path / "eval.toml"
    path.write_text('task = "Lift"\nmodel = "random:octo-small-1.5"\nperturb = ["camera:3", "noise:2"]\n')
    protocol = build_protocol(read_protocol_file(path))
    assert protocol.perturb == "camera@image_primary:3,noise:2"
    assert build_protocol({"task": ["Lift"], "model": "random:octo-small-1.5", "perturb": "texture:0"}).perturb is None


def test_tasks_that_cannot_take_a_perturbation_say_so():
    with pytest.raises(P.PerturbationError, match="Door cannot take distractors"):
        P.check_task(envs.get_task("Door"), P.parse_perturb("distractors:1"), ("image_primary",))
    with pytest.raises(P.PerturbationError, match="no camera 'image_side'"):
        P.check_task(envs.get_task("Lift"), P.parse_perturb("camera@image_side:1"), ("image_primary", "image_wrist"))
    with pytest.raises(P.PerturbationError, match="not for --instruction"):
        P.check_task(envs.get_task("Lift"), P.parse_perturb("language:2"), ("image_primary",), "lift it")
    P.check_task(envs.get_task("Lift"), P.parse_perturb("camera@image_wrist:2,language:2"), ("image_primary", "image_wrist"))


def test_paraphrases_come_from_the_stated_list_and_repeat_per_seed():
    task = envs.get_task("Stack")
    (p2,) = P.parse_perturb("language:2")
    said = {P.instruction_for(task, task.instruction, seed, (p2,)) for seed in range(40)}
    assert said <= set(task.paraphrases) and len(said) > 1
    assert P.instruction_for(task, task.instruction, 7, (p2,)) == P.instruction_for(task, task.instruction, 7, (p2,))
    assert P.instruction_for(task, task.instruction, 7, ()) == task.instruction
    assert P.instruction_for(task, task.instruction, 7, P.parse_perturb("language:1")) == "Stack the red cube on the green cube."
    assert P.instruction_for(task, task.instruction, 3, P.parse_perturb("language:5")).isupper()


def test_noise_is_drawn_per_seed_step_and_camera():
    frame = np.full((64, 64, 3), 120, np.uint8)
    (p,) = P.parse_perturb("noise:3")
    a = P.noise_frame(frame, 1, p, 0, "image_primary")
    assert np.array_equal(a, P.noise_frame(frame, 1, p, 0, "image_primary"))
    assert not np.array_equal(a, P.noise_frame(frame, 1, p, 1, "image_primary"))
    assert not np.array_equal(a, frame) and abs(float(a.mean()) - 120) < 3


def test_a_kind_s_draws_follow_its_name_not_its_place_in_the_table(monkeypatch):
    # the seven kinds keep the numbers their table positions gave them (the golden perturbed run holds the draws)
    assert P.KIND_SEEDS == {"camera": 0, "lighting": 1, "texture": 2, "distractors": 3, "init-state": 4, "noise": 5,
                            "language": 6}
    (camera,) = P.parse_perturb("camera:3")
    (noise,) = P.parse_perturb("noise:2")
    frame = np.full((32, 32, 3), 120, np.uint8)
    before = (P.camera_draw(5, camera), P.noise_frame(frame, 5, noise, 1, "image_primary"))
    monkeypatch.setattr(P, "KINDS", ("a-new-kind",) + tuple(reversed(P.KINDS)))  # a kind inserted, the rest reordered
    after = (P.camera_draw(5, camera), P.noise_frame(frame, 5, noise, 1, "image_primary"))
    assert all(np.array_equal(before[0][k], after[0][k]) for k in before[0]) and np.array_equal(before[1], after[1])
    new = P.kind_seed("a-new-kind")
    assert new == P.kind_seed("a-new-kind") and new not in P.KIND_SEEDS.values() and new != P.kind_seed("another-kind")


def test_distractor_placement_keeps_its_clearances():
    g = np.random.default_rng(0)
    avoid = np.array([[0.0, 0.0], [0.1, 0.05]])
    xy = P.place_distractors(g, np.array([-0.3, -0.3]), np.array([0.3, 0.3]), avoid, 5, 0.10, 0.07)
    assert np.linalg.norm(xy[:, None] - avoid[None], axis=-1).min() >= 0.10
    gaps = np.linalg.norm(xy[:, None] - xy[None], axis=-1)[~np.eye(5, dtype=bool)]
    assert gaps.min() >= 0.07
    with pytest.raises(P.PerturbationError, match="no room"):
        P.place_distractors(g, np.array([-0.05, -0.05]), np.array([0.05, 0.05]), avoid, 3, 0.10, 0.07)


def test_camera_draw_has_the_level_s_magnitudes():
    (p,) = P.parse_perturb("camera:4")
    draw = P.camera_draw(11, p)
    assert np.linalg.norm(draw["offset"]) == pytest.approx(0.08) and draw["degrees"] == 8.0
    assert abs(draw["fovy_delta"]) == 4.0
    pos, quat, fovy = P.perturbed_camera(np.zeros(3), np.array([1.0, 0, 0, 0]), 45.0, draw)
    angle = 2 * np.degrees(np.arccos(np.clip(abs(quat[0]), 0, 1)))
    assert angle == pytest.approx(8.0) and fovy == 45.0 + draw["fovy_delta"]


# ------------------------------------------------------------------------------------------- simulator

def _frames(env, seed, steps=2):
    obs, info = env.reset(seed=seed)
    out = [obs["image_primary"].copy()]
    for _ in range(steps):
        obs, *_ = env.step(np.zeros(7, np.float32))
        out.append(obs["image_primary"].copy())
    return np.stack(out), info


@pytest.mark.slow
def test_level_zero_is_the_nominal_scene_bit_for_bit():
    plain = envs.make("Lift", fast_render=True)
    zero = envs.make("Lift", fast_render=True, perturb="camera:0,lighting:0,distractors:0,noise:0,texture:0")
    try:
        a, _ = _frames(plain, 5)
        b, _ = _frames(zero, 5)
        assert np.array_equal(a, b)
    finally:
        plain.close()
        zero.close()


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["camera:3,lighting:3,texture:3", "distractors:3,init-state:3,noise:3"])
def test_same_seed_and_level_give_the_same_frames_twice_and_in_a_fresh_env(spec):
    env = envs.make("Stack", fast_render=True, perturb=spec)
    try:
        first, _ = _frames(env, 2)
        _frames(env, 9)  # another episode between: nothing carries over
        again, _ = _frames(env, 2)
        other, _ = _frames(env, 3)
    finally:
        env.close()
    fresh_env = envs.make("Stack", fast_render=True, perturb=spec)
    try:
        fresh, _ = _frames(fresh_env, 2)
    finally:
        fresh_env.close()
    assert np.array_equal(first, again) and np.array_equal(first, fresh)
    assert not np.array_equal(first, other)
    nominal = envs.make("Stack", fast_render=True)
    try:
        assert not np.array_equal(first[0], _frames(nominal, 2, steps=0)[0][0])
    finally:
        nominal.close()


def _target_centroid(mask: np.ndarray) -> np.ndarray:
    rows, cols = np.nonzero(mask)
    return np.array([rows.mean(), cols.mean()])


@pytest.mark.slow
def test_camera_shift_moves_the_target_by_the_predicted_pixels():
    seed, size = 4, 256
    nominal = envs.make("Lift", masks=True, fast_render=True)
    shifted = envs.make("Lift", masks=True, fast_render=True, perturb="camera:3")
    try:
        _, info0 = nominal.reset(seed=seed)
        _, info1 = shifted.reset(seed=seed)
        model = nominal.robosuite_env.sim.model
        cam = model.camera_name2id("agentview")
        centre = nominal.target_centres()
        assert np.allclose(centre, shifted.target_centres())  # the scene did not move, only the camera
        pos, quat, fovy = np.array(model.cam_pos[cam]), np.array(model.cam_quat[cam]), float(model.cam_fovy[cam])
        (p,) = P.parse_perturb("camera:3")
        new_pos, new_quat, new_fovy = P.perturbed_camera(pos, quat, fovy, P.camera_draw(seed, p))

        def mat(q):
            w, x, y, z = q
            return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                             [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                             [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])

        # agentview hangs on the world body: its model pose is its world pose
        assert np.allclose(nominal.robosuite_env.sim.data.cam_xpos[cam], pos)
        predicted = (project_points(centre, new_pos, mat(new_quat), new_fovy, size, size)
                     - project_points(centre, pos, mat(quat), fovy, size, size))[0]
        seen = _target_centroid(info1["masks"]["image_primary"]["target"]) - \
            _target_centroid(info0["masks"]["image_primary"]["target"])
        assert np.linalg.norm(predicted) > 5  # level 3 moves it visibly
        assert np.linalg.norm(seen - predicted) < 1.5, (seen, predicted)
    finally:
        nominal.close()
        shifted.close()


@pytest.mark.slow
def test_distractor_masks_cover_distractors_and_never_the_target():
    env = envs.make("Lift", masks=True, fast_render=True, perturb="distractors:5")
    try:
        for seed in (0, 1):
            _, info = env.reset(seed=seed)
            masks = info["masks"]["image_primary"]
            names = [f"distractor_{i}" for i in range(5)]
            assert set(names) <= set(masks)
            assert sum(int(masks[n].sum()) > 0 for n in names) >= 4  # the robot may hide one
            for n in names:
                assert not (masks[n] & masks["target"]).any() and not (masks[n] & masks["background"]).any()
            placed = np.array([d["xy"] for d in env.perturbation_record["distractors"]])
            target = env.target_centres()[0, :2]
            assert np.linalg.norm(placed - target, axis=1).min() >= P.MAGNITUDES["distractors"]["clearance_m"]
    finally:
        env.close()


@pytest.mark.slow
def test_lighting_levels_darken_the_frame():
    means = []
    for level in (0, 1, 3, 5):
        env = envs.make("Lift", fast_render=True, perturb=f"lighting:{level}")
        try:
            obs, _ = env.reset(seed=6)
            means.append(float(obs["image_primary"].mean()))
        finally:
            env.close()
    assert means[0] > means[1] > means[2] > means[3], means


@pytest.mark.slow
def test_noise_changes_what_the_policy_is_fed_not_the_scene():
    env = envs.make("Lift", masks=True, fast_render=True, perturb="noise:4")
    plain = envs.make("Lift", masks=True, fast_render=True)
    try:
        obs, info = env.reset(seed=1)
        obs0, info0 = plain.reset(seed=1)
        clean = env._renderer.rgb("image_primary")
        assert np.array_equal(clean, obs0["image_primary"])  # the rendered scene is the nominal one
        assert not np.array_equal(obs["image_primary"], clean)  # the policy is fed the noisy frame
        assert np.array_equal(info["masks"]["image_primary"]["target"], info0["masks"]["image_primary"]["target"])
        assert env.perturbation_record["noise"]["jpeg_quality"] == 90 - 14 * 4
    finally:
        env.close()
        plain.close()


@pytest.mark.slow
def test_texture_changes_the_arena_never_the_target():
    env = envs.make("Lift", masks=True, fast_render=True, perturb="texture:5")
    plain = envs.make("Lift", masks=True, fast_render=True)
    try:
        obs, info = env.reset(seed=2)
        obs0, _ = plain.reset(seed=2)
        target = info["masks"]["image_primary"]["target"]
        background = info["masks"]["image_primary"]["background"]
        frame, frame0 = obs["image_primary"].astype(int), obs0["image_primary"].astype(int)
        assert np.abs(frame - frame0)[background].mean() > 10
        # the cube keeps its own colour (lighting and reflections of the arena may tint its edges slightly)
        assert np.abs(frame[target].mean(axis=0) - frame0[target].mean(axis=0)).max() < 12
    finally:
        env.close()
        plain.close()


@pytest.mark.slow
def test_a_paraphrase_is_the_instruction_the_env_reports():
    env = envs.make("Lift", fast_render=True, perturb="language:2")
    try:
        _, info = env.reset(seed=0)
        assert info["instruction"] in envs.get_task("Lift").paraphrases
        assert env.perturbation_record["instruction"] == info["instruction"]
    finally:
        env.close()


# ------------------------------------------------------------------------------------------- hostile input

def test_a_foreign_perturb_in_a_manifest_is_one_line(tmp_path):
    from harness.runfolder.schema import MalformedRunError, check_protocol

    good = Protocol(model="random:octo-small-1.5", tasks=("Lift",), perturb="camera:2").to_dict()
    with pytest.raises(MalformedRunError, match="protocol.perturb"):
        check_protocol({**good, "perturb": 5}, "manifest.json")
    with pytest.raises(ValueError, match="level must be 0"):
        Protocol.from_dict({**good, "perturb": "camera:99"})


@pytest.mark.parametrize("argv, fragment", [
    (["--perturb", "camera,blur"], "unknown kind"),
    (["--perturb", "camera", "--levels", "0,7"], "--levels"),
    (["--perturb", "camera", "--levels", "x"], "--levels"),
    (["--perturb", "lighting@image_primary"], "only camera and noise"),
    (["--perturb", "distractors", "--task", "Door"], "Door cannot take distractors"),
])
def test_robustness_refuses_bad_grids_in_one_line_before_loading(tmp_path, capsys, argv, fragment):
    from harness import cli

    args = ["robustness", "--model", "random:octo-small-1.5", "--task", "Lift", "--out", str(tmp_path / "g"), *argv]
    assert cli.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and fragment in err[0], err


def test_robustness_refuses_a_foreign_grid_file(tmp_path, capsys):
    from harness import cli

    (tmp_path / "g").mkdir()
    (tmp_path / "g" / "robustness.json").write_text("[1, 2]")
    assert cli.main(["robustness", "--model", "random:octo-small-1.5", "--task", "Lift", "--perturb", "camera",
                     "--out", str(tmp_path / "g")]) == 2
    assert "not a robustness grid file" in capsys.readouterr().err


def test_point_biserial_matches_scipy_and_its_interval_is_fisher_z():
    from scipy.stats import pearsonr, pointbiserialr

    from harness.analysis.robustness import js_divergence_bits, point_biserial

    rng = np.random.default_rng(0)
    success = rng.integers(0, 2, 40)
    mass = 0.6 + 0.1 * rng.normal(size=40) - 0.05 * success
    r, low, high, n = point_biserial(success, mass)
    assert n == 40 and r == pytest.approx(pointbiserialr(success, mass).statistic, abs=1e-12)
    ci = pearsonr(success, mass).confidence_interval(0.95)  # scipy's Fisher-z interval of Pearson's r
    assert (low, high) == pytest.approx((ci.low, ci.high), abs=1e-9)
    assert np.isnan(point_biserial([1, 1, 1, 1, 1], [0.1, 0.2, 0.3, 0.4, 0.5])[0])  # no variation: no estimate
    p = np.array([[0.5, 0.5, 0.0], [1.0, 0.0, 0.0]])
    q = np.array([[0.0, 0.5, 0.5], [0.0, 1.0, 0.0]])
    assert js_divergence_bits(p, q) == pytest.approx([0.5, 1.0])  # half-overlapping halves; disjoint: 1 bit


def test_a_cell_breaks_a_task_only_when_its_paired_drop_survives_holm():
    from harness.analysis.robustness import EpisodeRow, paired_rows, success_rows, verdict_line

    def cell(run, condition, level, outcomes, status=None):
        return [EpisodeRow(run, "Lift", condition, level, seed, seed, (status or {}).get(seed, "ok"), ok,
                           0.8, 0.5, 0.0, 0.8) for seed, ok in enumerate(outcomes)]

    nominal = cell("nominal", "nominal", 0, [True] * 20)
    texture = cell("texture-5", "texture", 5, [False] * 20)  # 20 discordant pairs: p = 2 * 0.5**20
    lighting = cell("lighting-5", "lighting", 5, [True] * 16 + [False] * 4)  # 4 lost: p = 0.125, not a break
    camera = cell("camera-3", "camera@image_primary", 3, [False] * 6 + [True] * 14, status={0: "failed", 1: "failed"})
    rows = nominal + texture + lighting + camera
    paired = {p.run: p for p in paired_rows(rows)}
    t, lt, c = paired["texture-5"], paired["lighting-5"], paired["camera-3"]
    assert (t.pairs, t.nominal_only, t.perturbed_only, t.breaks) == (20, 20, 0, True)
    assert t.p_mcnemar == pytest.approx(2 * 0.5 ** 20)
    assert t.p_holm == pytest.approx(3 * t.p_mcnemar)  # the smallest of three p-values, times three
    assert (lt.nominal_only, lt.breaks) == (4, False) and lt.p_mcnemar == pytest.approx(0.125)
    assert (c.pairs, c.nominal_only) == (18, 4) and not c.breaks  # errored episodes are not pairs: 4 lost of 18, not 6 of 20
    text = verdict_line("Lift", success_rows(rows), paired_rows(rows))
    assert text == "Lift: nominal 20/20. Breaks under texture 5. Other cells: 0 HOLD, 2 UNDETERMINED."
    assert (t.perturbed_successes, t.nominal_successes) == (0, 20)  # the figures behind it, in the cell's row
    gained = cell("noise-1", "noise", 1, [True] * 20)
    worse_nominal = cell("nominal", "nominal", 0, [False] * 20)
    assert not paired_rows(worse_nominal + gained)[0].breaks  # gaining successes never "breaks"
    assert "No cell breaks it." in verdict_line("Lift", [], paired_rows(worse_nominal + gained))


def test_the_association_interval_resamples_seeds_and_needs_both_outcomes():
    from harness.analysis.robustness import MIN_CLASS, EpisodeRow, association_rows, association_table, seed_cluster_interval

    rng = np.random.default_rng(1)
    seeds = np.repeat(np.arange(20), 4)  # one seed's episodes across four conditions share its scene
    per_seed = rng.normal(size=20)[seeds]
    success = (per_seed + 0.3 * rng.normal(size=80)) > 0
    mass = 0.8 - 0.05 * per_seed + 0.01 * rng.normal(size=80)  # more nuisance mass on the seeds that fail
    low, high = seed_cluster_interval(seeds, success, mass)
    assert high < 0 and low < np.corrcoef(success, mass)[0, 1] < high
    assert seed_cluster_interval(seeds, success, mass) == (low, high)  # seeded: the same interval twice
    # treating the 80 episodes as independent (80 clusters) gives a narrower interval than 20 seeds do
    independent = seed_cluster_interval(np.arange(80), success, mass)
    assert independent[1] - independent[0] < high - low
    few = np.zeros(80, bool)
    few[:MIN_CLASS - 1] = True  # too few successes: no interval, and the sentence says so
    assert all(np.isnan(seed_cluster_interval(seeds, few, mass)))
    rows = [EpisodeRow("r", "Lift", "nominal", 0, int(k), i, "ok", bool(ok), float(m), 0.5, 0.0, float(m), float(m))
            for i, (k, ok, m) in enumerate(zip(seeds, few, mass))]
    table = association_table("Lift", association_rows(rows))
    assert table and all(row[5] == f"too few seeds, successes or failures (< {MIN_CLASS})" for row in table)
    assert not any("nan" in cell for row in table for cell in row)


def test_a_condition_that_moves_both_success_and_nuisance_mass_is_not_a_within_condition_association():
    from harness.analysis.robustness import EpisodeRow, association_rows

    rng = np.random.default_rng(2)
    rows = []
    for run, rate, shift in (("nominal", 0.9, 0.0), ("texture-5", 0.1, -0.1)):  # the perturbation lowers both
        for seed in range(40):
            rows.append(EpisodeRow(run, "Lift", run, 0, seed, seed, "ok", bool(rng.random() < rate),
                                   float(0.85 + shift + 0.01 * rng.normal()), 0.5, 0.0, 0.8, 0.8))
    a = association_rows(rows)[0]
    assert a[5] > 0  # pooled: "more nuisance mass goes with success", made by the condition alone
    assert a[14] < 0 < a[15]  # within conditions the seed-cluster interval holds 0

"""Sanity checks of attribution methods and of the deletion metric (issue 29), on models whose answer is known:
model-parameter randomisation, the imputation fill, MoRF/LeRF, additivity of single-patch effects, the
`octo-harness sanity` command on the committed baseline's recorded inputs."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import spearmanr

from harness.measures import attribution as A
from harness.measures import faithfulness as F
from harness.analysis import sanity as S
from harness.octo.tokens import TokenMap

ROWS = COLS = 4
PATCH = 4
N = ROWS * COLS
TARGET = 6
ROOT = Path(__file__).resolve().parents[2]


def tokens() -> TokenMap:
    group = np.array(["obs_primary"] * N + ["readout_action"], dtype="U32")
    row = np.array([i // COLS for i in range(N)] + [-1], np.int32)
    col = np.array([i % COLS for i in range(N)] + [-1], np.int32)
    return TokenMap(group, np.zeros(N + 1, np.int32), row, col, (("obs_primary", "image_primary", ROWS, COLS),),
                    np.array([N], np.int32))


def patch_means(frame):
    return frame.reshape(ROWS, PATCH, COLS, PATCH, 3).mean(axis=(1, 3, 4)).reshape(-1) / 255.0  # (16,)


def weighted_step(params: dict, image: np.ndarray) -> A.StepFunction:
    """A 'policy' with parameters: action = 100 * sum_j w_j * mean(patch j) (every number of the (4, 7) chunk),
    plus a fixed offset; attention uniform. `params = {"head": {"w": (16,)}}`."""
    w = jnp.asarray(params["head"]["w"])

    def fn(images, perturbation):
        x = patch_means(images["image_primary"][-1])
        attention = jnp.full((N + 1, N + 1), 1.0 / (N + 1)) + perturbation[0, 0]
        out = 100.0 * jnp.dot(w, x) * attention[N, :N].sum() * (N + 1) / N
        actions = jnp.broadcast_to(out, (4, 7)) + jnp.linspace(0.1, 0.2, 28).reshape(4, 7)
        return actions, attention[None, None]

    batched = jax.jit(jax.vmap(lambda imgs: fn(imgs, jnp.zeros((1, 1, N + 1, N + 1)))[0]))
    return A.StepFunction(fn=jax.jit(fn), batch=lambda imgs: np.asarray(batched(imgs)),
                          images={"image_primary": image[None].astype(np.float32)}, tokens=tokens(), shape=(1, 1, N + 1))


# ------------------------------------------------------------------------------------------- similarity measures


def test_spearman_and_ssim_known_values():
    rng = np.random.default_rng(0)
    a, b = rng.random((4, 4)), rng.random((4, 4))
    assert S.spearman(a, a) == pytest.approx(1.0)
    assert S.spearman(a, -a) == pytest.approx(-1.0)
    assert S.spearman(a, b) == pytest.approx(spearmanr(a.ravel(), b.ravel()).statistic)
    assert S.spearman(np.array([1, 1, 2, 3.0]), np.array([1, 2, 3, 4.0])) == pytest.approx(
        spearmanr([1, 1, 2, 3], [1, 2, 3, 4]).statistic)  # ties: average ranks
    assert np.isnan(S.spearman(np.ones(4), a.ravel()[:4]))
    assert S.ssim(a, a) == pytest.approx(1.0)
    assert S.ssim(a, 3 * a + 2) == pytest.approx(1.0)  # scaled to [0, 1] first
    assert S.ssim(a, -a) < 0
    # by hand: x = [0, 1], y = [1, 0] after scaling: means 0.5, variances 0.25, covariance -0.25
    expected = (2 * 0.25 + S.SSIM_C1) * (-0.5 + S.SSIM_C2) / ((0.5 + S.SSIM_C1) * (0.5 + S.SSIM_C2))
    assert S.ssim(np.array([0.0, 1.0]), np.array([1.0, 0.0])) == pytest.approx(expected)
    with pytest.raises(ValueError, match="differ in size"):
        S.spearman(np.ones(3), np.ones(4))


# ------------------------------------------------------------------------------------------- randomisation


def octo_like_tree():
    rng = np.random.default_rng(1)
    block = lambda: {"MultiHeadDotProductAttention_0": {"kernel": rng.normal(0, 1, (4, 4)).astype(np.float32)}}  # noqa: E731
    return {"heads_action": {"mean_proj": {"kernel": rng.normal(0, 1, (8, 3)).astype(np.float32)}},
            "octo_transformer": {"BlockTransformer_0": {"Transformer_0": {
                "encoderblock_0": block(), "encoderblock_1": block(), "encoder_norm": {"scale": np.ones(4, np.float32)}}},
                "obs_primary_projection": {"kernel": rng.normal(0, 1, (4, 4)).astype(np.float32)}}}


def test_blocks_schedules_and_redrawn_weights():
    tree = octo_like_tree()
    blocks = S.octo_blocks(tree)
    assert [name for name, _ in blocks] == ["head", "block_1", "block_0", "stem"]
    assert ("octo_transformer", "BlockTransformer_0", "Transformer_0", "encoder_norm") in blocks[1][1]  # with the top block
    stages = S.schedules(blocks)
    assert [s[1] for s in stages if s[0] == "cascading"] == ["up to head", "up to block_1", "up to block_0", "up to stem"]
    assert len(stages[3][2]) == sum(len(p) for _, p in blocks)  # the last cascade stage randomises everything
    assert [s[1] for s in stages if s[0] == "independent"] == ["head", "block_1", "block_0", "stem"]

    cascade = S.randomised_params(tree, stages[1][2], seed=0)  # head + block_1
    alone = S.randomised_params(tree, [blocks[1][1][0]], seed=0)  # block_1 alone
    t = tree["octo_transformer"]["BlockTransformer_0"]["Transformer_0"]
    c = cascade["octo_transformer"]["BlockTransformer_0"]["Transformer_0"]
    a = alone["octo_transformer"]["BlockTransformer_0"]["Transformer_0"]
    kernel = lambda d, b: d[b]["MultiHeadDotProductAttention_0"]["kernel"]  # noqa: E731
    assert not np.allclose(kernel(c, "encoderblock_1"), kernel(t, "encoderblock_1"))
    np.testing.assert_array_equal(kernel(c, "encoderblock_1"), kernel(a, "encoderblock_1"))  # same draw in both schedules
    assert kernel(c, "encoderblock_0") is kernel(t, "encoderblock_0")  # untouched blocks are shared, not copied
    assert kernel(c, "encoderblock_1").dtype == np.float32 and kernel(c, "encoderblock_1").shape == (4, 4)
    np.testing.assert_array_equal(c["encoder_norm"]["scale"], np.ones(4))  # a constant array stays constant
    assert np.std(cascade["heads_action"]["mean_proj"]["kernel"]) == pytest.approx(
        np.std(tree["heads_action"]["mean_proj"]["kernel"]), rel=0.5)
    assert not np.allclose(tree["heads_action"]["mean_proj"]["kernel"], cascade["heads_action"]["mean_proj"]["kernel"])
    with pytest.raises(KeyError, match="not in the model"):
        S.randomised_params(tree, [("octo_transformer", "nope")], seed=0)


@pytest.mark.slow
def test_randomisation_known_answer_one_patch_model():
    """Trained: the action depends on patch TARGET alone, so saliency and occlusion rank it first; re-drawn weights
    (N(mean, std) of the one-hot vector) spread the dependence over every patch, and the maps stop ranking it first.
    Over steps, the Spearman correlation with the trained map is low: saliency and occlusion PASS; the random map,
    which never looks at the weights, FAILS (the check can fail)."""
    trained = {"head": {"w": np.eye(N)[TARGET].astype(np.float32)}}
    randomised = S.randomised_params(trained, [("head",)], seed=3)
    assert np.argmax(np.abs(randomised["head"]["w"])) != TARGET
    rows = []
    for step in range(8):
        image = np.random.default_rng(step).uniform(0, 255, (ROWS * PATCH, COLS * PATCH, 3))
        maps = {}
        for name, params in (("trained", trained), ("randomised", randomised)):
            analysis = A.analyse(weighted_step(params, image), occlusion=True)
            maps[name] = {m: A.attribute(analysis, m, seed=[0, step]) for m in ("saliency", "occlusion", "random")}
        for m in ("saliency", "occlusion"):
            assert F.ranking(maps["trained"][m]["image_primary"])[0] == TARGET
            assert F.ranking(maps["randomised"][m]["image_primary"])[0] != TARGET
        rows += [{"schedule": "cascading", "stage": "up to head", **r} for r in S.compare_maps(maps["trained"], maps["randomised"])]
    summary = S.summarise_randomisation(rows)
    verdicts = S.verdict(summary, "up to head")
    assert verdicts[("saliency", "image_primary")] == "pass"
    assert verdicts[("occlusion", "image_primary")] == "pass"
    assert verdicts[("random", "image_primary")] == "fail"
    random_row = next(r for r in summary if r["method"] == "random")
    assert random_row["spearman"] == 1.0 and random_row["ssim"] == pytest.approx(1.0) and random_row["steps"] == 8
    saliency = next(r for r in summary if r["method"] == "saliency")
    assert saliency["spearman_low"] <= saliency["spearman"] <= saliency["spearman_high"] < S.PASS_BELOW


def test_verdict_needs_an_interval():
    rows = [{"schedule": "cascading", "stage": "up to stem", "method": "saliency", "camera": "c", "spearman": 0.1, "ssim": 0.2}]
    assert S.verdict(S.summarise_randomisation(rows), "up to stem") == {("saliency", "c"): "n/a"}  # one step: no interval


# ------------------------------------------------------------------------------------------- the imputation fill


def test_imputation_of_a_constant_image_returns_it():
    image = np.full((32, 32, 3), 77.0, np.float32)
    deleted = np.zeros((4, 4), bool)
    deleted[1:3, 0:3] = True
    pixels = F.pixel_mask(deleted[None], 32, 32)[0]
    for factor in (1, 2, 4):
        np.testing.assert_array_equal(F.impute(image, pixels, noise=0, factor=factor), image)
    everything = np.ones((1, 4, 4), bool)  # nothing kept: the anchor (the image's mean) decides
    np.testing.assert_allclose(F.delete_patches(image, everything, "impute")[0], 77.0, atol=6 * F.IMPUTE_NOISE)
    noisy = F.delete_patches(image, deleted[None], "impute", seed=1)[0]
    np.testing.assert_array_equal(noisy[~pixels], image[~pixels])  # kept pixels untouched
    assert abs(noisy[pixels].mean() - 77.0) < 0.5 and 0.5 * F.IMPUTE_NOISE < noisy[pixels].std() < 2 * F.IMPUTE_NOISE
    np.testing.assert_array_equal(noisy, F.delete_patches(image, deleted[None], "impute", seed=1)[0])  # seeded


def test_imputation_continues_a_linear_ramp_and_is_not_a_flat_fill():
    """The neighbour average reproduces a linear image (it is harmonic), so the deleted hole is filled with the ramp
    itself; mean fill leaves a flat block there (the shape leak ROAD removes)."""
    y, x = np.mgrid[0:32, 0:32]
    ramp = np.repeat((40 + 3 * x + 2 * y)[..., None], 3, axis=2).astype(np.float32)
    deleted = np.zeros((1, 4, 4), bool)
    deleted[0, 1:3, 1:3] = True
    pixels = F.pixel_mask(deleted, 32, 32)[0]
    exact = F.impute(ramp, pixels, noise=0)
    np.testing.assert_allclose(exact[pixels], ramp[pixels], atol=0.5)
    blocky = F.impute(ramp, pixels, noise=0, factor=2)  # blocks: the ramp up to the block averaging
    np.testing.assert_allclose(blocky[pixels], ramp[pixels], atol=3.0)
    flat = F.delete_patches(ramp, deleted, "mean")[0]
    assert np.abs(flat[pixels] - ramp[pixels]).max() > 20


def test_impute_rejects_bad_input():
    with pytest.raises(ValueError, match="does not match"):
        F.impute(np.zeros((8, 8, 3)), np.zeros((4, 4), bool))
    with pytest.raises(ValueError, match="must divide"):
        F.impute(np.zeros((8, 8, 3)), np.zeros((8, 8), bool), factor=3)
    with pytest.raises(ValueError, match="depends on the deleted region"):
        F.baseline_image(np.zeros((8, 8, 3)), "impute")
    assert F.impute_factor(128, 128, 8, 8) == 4 and F.impute_factor(64, 64, 4, 4) == 4
    assert F.impute_factor(30, 30, 4, 4) == 1  # no divisor above 1 fits both
    huge = np.full((16, 16, 3), 1e30, np.float32)
    out = F.delete_patches(huge, np.ones((1, 4, 4), bool), "impute")
    assert np.isfinite(out).all() and out.max() <= 255  # clipped to the pixel range


# ------------------------------------------------------------------------------------------- MoRF / LeRF, additivity


def test_lerf_stays_flat_for_the_faithful_map_and_rows_name_the_fill():
    image = np.random.default_rng(0).uniform(0, 255, (16, 16, 3))
    step = weighted_step({"head": {"w": np.eye(N)[TARGET].astype(np.float32)}}, image)
    analysis = A.analyse(step, occlusion=True)
    maps = {m: A.attribute(analysis, m) for m in ("occlusion", "random")}
    for fill in F.FILLS:
        rows = F.step_faithfulness(step.batch, step.images, analysis.actions, maps, fill=fill, seed=[0, 1])
        occ = next(r for r in rows if r["method"] == "occlusion")
        assert occ["fill"] == fill
        assert max(occ["lerf_curve"][:-1]) < 1e-3 * occ["change_all"]  # the one patch that matters is deleted last
        assert occ["lerf_auc"] < 0.2 * occ["random_lerf_auc"]
        assert occ["deletion_auc"] > 1.2 * occ["random_deletion_auc"]
        assert occ["bottom_k/1"] == occ["lerf_curve"][1]


def staircase(image_value: float = 60.0, signal: float = 120.0):
    """An image constant except for 4 separated bright patches; the additive model weighs only those."""
    image = np.full((16, 16, 3), image_value)
    w = np.zeros(N, np.float32)
    for p, weight in zip((0, 2, 8, 10), (0.1, 0.4, 0.2, 0.3)):
        r, c = divmod(p, COLS)
        image[r * PATCH:(r + 1) * PATCH, c * PATCH:(c + 1) * PATCH] = image_value + signal
        w[p] = weight
    return image.astype(np.float32), {"head": {"w": w}}


@pytest.mark.parametrize("fill", F.FILLS)
def test_additive_model_deletion_gives_the_occlusion_rankings_curve(fill):
    """action = sum_p w_p * mean(patch p): deleting a set changes it by the sum of the single-patch changes, so the
    occlusion map's deletion curve is the running sum of the sorted single effects and beats every other ranking.
    Exact for mean and blur (the fill of a patch does not depend on the other deleted patches); impute fills a
    patch from whatever surrounds it, so there the curve holds to a few percent, up to the last point: with every
    patch deleted nothing is left to impute from and the fill is the image's mean colour (bright patches included)."""
    image, params = staircase()
    step = weighted_step(params, image)
    reference = np.asarray(step.fn(step.images, jnp.zeros((1, 1, N + 1, N + 1)))[0])
    single = A.occlusion_maps(step, reference, fill)["image_primary"]
    maps = {"occlusion": {"image_primary": single}, "random": {"image_primary": np.random.default_rng(0).random((ROWS, COLS))}}
    rows = F.step_faithfulness(step.batch, step.images, reference, maps, fill=fill, seed=[0])
    occ = next(r for r in rows if r["method"] == "occlusion")
    expected = np.concatenate([[0.0], np.cumsum(np.sort(single.ravel())[::-1])])
    if fill == "impute":
        np.testing.assert_allclose(occ["deletion_curve"][:-1], expected[:-1], atol=0.05 * expected[-1])
    else:
        np.testing.assert_allclose(occ["deletion_curve"], expected, atol=1e-4)
    assert occ["deletion_auc"] >= occ["random_deletion_auc"]
    assert occ["deletion_auc"] >= next(r for r in rows if r["method"] == "random")["deletion_auc"]


def test_patch_effects_additive_and_interacting():
    image, params = staircase()
    step = weighted_step(params, image)
    reference = np.asarray(step.fn(step.images, jnp.zeros((1, 1, N + 1, N + 1)))[0])

    def evaluate(frames, batch=step.batch):
        return batch({"image_primary": frames[:, None]})

    sets = {"first": S.nested_sets(np.arange(N), [1, 4, 16], ROWS, COLS)}
    additive = S.patch_effects(evaluate, image, reference, sets, fill="mean")
    np.testing.assert_allclose(additive["first"]["additivity"], 1.0, rtol=1e-5)
    np.testing.assert_allclose(additive["first"]["cosine"], 1.0, rtol=1e-5)
    assert additive["whole"] == pytest.approx(additive["first"]["change"][-1])

    def either(frames):  # a policy that reacts when ANY of patches 0 and 2 is dark: a jointly used pair
        x = np.stack([patch_means(f) for f in frames])  # (m, 16)
        out = 10.0 * np.maximum(x[:, 0], x[:, 2])
        return np.broadcast_to(out[:, None, None], (len(frames), 4, 7))

    ref = either(image[None])[0]
    pair = {"pair": np.zeros((1, ROWS, COLS), bool)}
    pair["pair"][0, 0, 0] = pair["pair"][0, 0, 2] = True
    joint = S.patch_effects(either, image, ref, pair, fill="mean")
    assert joint["single"][0, 0] == 0 and joint["single"][0, 2] == 0  # alone, either patch is redundant
    assert joint["pair"]["change"][0] > 0 and not np.isfinite(joint["pair"]["additivity"][0])  # jointly they matter


# ------------------------------------------------------------------------------------------- the command


@pytest.mark.slow
def test_sanity_command_on_the_committed_baselines_recorded_inputs(tmp_path, capsys):
    """The real reference policy on the committed baseline's recorded inputs: every block's randomisation changes
    the maps (the cascade's last stage leaves no attention layer intact), the random map is unchanged, files are
    written, and the additivity rows cover both cameras and fills."""
    from harness.cli import main

    out = tmp_path / "sanity"
    # --model: the baseline records the absolute model path of the checkout that made it, absent on other machines
    code = main(["sanity", str(ROOT / "results/baselines/reference-lift"), "--model",
                 str(ROOT / "models/octo-reference-robosuite"), "--every", "50", "--max-steps", "2",
                 "--methods", "attention:3,saliency", "--additivity", "--fills", "mean,impute", "--out", str(out)])
    assert code == 0
    result = json.loads((out / "sanity.json").read_text())
    assert result["steps"] == 2
    assert [b["name"] for b in result["blocks"]] == ["head", "block_3", "block_2", "block_1", "block_0", "stem"]
    rows = {(r["schedule"], r["stage"], r["method"], r["camera"]): r for r in result["randomisation"]}
    for camera in ("image_primary", "image_wrist"):
        assert rows[("cascading", "up to stem", "random", camera)]["spearman"] == 1.0
        assert rows[("cascading", "up to stem", "attention:3", camera)]["spearman"] < 0.9
        # the head sits above the attention: re-drawing it alone leaves layer-3 attention exactly as it was
        assert rows[("independent", "head", "attention:3", camera)]["spearman"] == pytest.approx(1.0)
        assert rows[("cascading", "up to stem", "random", camera)]["verdict"] == "fail"
    assert {(r["camera"], r["fill"]) for r in result["additivity"]} == {
        (c, f) for c in ("image_primary", "image_wrist") for f in ("mean", "impute")}
    assert (out / "randomisation.csv").read_text().startswith("schedule,stage,method,camera")
    profile = {(r["camera"], r["method"]): np.asarray(r["map_share"]) for r in result["patch_profile"]}
    assert profile[("image_wrist", "saliency")].shape == (4, 4) and profile[("image_primary", "saliency")].shape == (8, 8)
    assert profile[("image_wrist", "saliency")].sum() == pytest.approx(1.0, abs=1e-3)
    assert (profile[("image_wrist", "pixel std over steps")] >= 0).all()
    assert result["occlusion_agreement"] == []  # occlusion was not among the methods
    assert "| cascading | up to stem |" in capsys.readouterr().out


def test_sanity_command_bad_input_is_one_line(tmp_path, capsys):
    from harness.cli import main

    assert main(["sanity", str(tmp_path), "--every", "0"]) == 2
    assert "--every must be >= 1" in capsys.readouterr().err
    assert main(["sanity", str(tmp_path), "--fills", "mean,sepia"]) == 2
    assert "unknown fill 'sepia'" in capsys.readouterr().err
    assert main(["sanity", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and len(err.strip().splitlines()) == 1


def test_sanity_command_names_the_fix_for_a_run_without_recorded_inputs(tmp_path, capsys):
    import shutil

    from harness.cli import main
    from tests.runfolder.edits import drop_output

    copy = tmp_path / "run"
    shutil.copytree(ROOT / "results/baselines/reference-lift", copy)
    drop_output(copy, "inputs.npz", rows=1)  # its first episode recorded no inputs
    assert main(["sanity", str(copy), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "--record-inputs" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()  # nothing written, nothing loaded


def test_profile_agreement_with_occlusion_and_static_patches():
    """Maps that rank patches as occlusion does agree (+1), reversed ones disagree (-1); the per-patch pixel spread
    over steps is 0 for a patch that never changes."""
    from harness.gate.sanity import _patch_means, _profile

    occ = np.arange(N, dtype=float).reshape(ROWS, COLS)
    agreement, profiles, frames = [], {}, {}
    for step in range(3):
        image = np.zeros((1, 16, 16, 3), np.float32)
        image[0, 12:, 12:] = 40.0 * step  # only the last patch changes over the steps
        trained = {"occlusion": {"image_primary": occ}, "same": {"image_primary": 2 * occ},
                   "reversed": {"image_primary": -occ + N}}
        _profile(trained, {"image_primary": image}, {"step": step}, agreement, profiles, frames)
    by = {(r["method"], r["step"] if "step" in r else 0): r["spearman"] for r in agreement}
    assert all(v == pytest.approx(1.0) for (m, _), v in by.items() if m == "same")
    assert all(v == pytest.approx(-1.0) for (m, _), v in by.items() if m == "reversed")
    assert len(agreement) == 6 and len(profiles[("image_primary", "same")]) == 3
    np.testing.assert_allclose(profiles[("image_primary", "same")][0].sum(), 1.0)
    spread = _patch_means(frames["image_primary"]).std(axis=0).mean(axis=-1)  # (4, 4)
    assert spread[3, 3] > 30 and np.all(spread.ravel()[:-1] == 0)

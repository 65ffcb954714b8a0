"""Attribution methods and faithfulness metrics on models whose answer is known."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from harness.measures import attribution as A
from harness.measures import faithfulness as F
from harness.octo.tokens import TokenMap

ROWS = COLS = 4
PATCH = 4  # pixels per patch side
TARGET = 6  # the one patch the toy policy reads (row 1, col 2)


def toy_tokens() -> TokenMap:
    """One camera of 4x4 patches (keys 0..15) and one readout (key 16), window 1."""
    n = ROWS * COLS
    group = np.array(["obs_primary"] * n + ["readout_action"], dtype="U32")
    row = np.array([i // COLS for i in range(n)] + [-1], np.int32)
    col = np.array([i % COLS for i in range(n)] + [-1], np.int32)
    return TokenMap(group, np.zeros(n + 1, np.int32), row, col, (("obs_primary", "image_primary", ROWS, COLS),),
                    np.array([n], np.int32))


def toy_fn(images, perturbation):
    """A one-layer, one-head 'policy' whose readout averages patch values, of which only TARGET is non-zero.

    Tokens: the mean pixel of each patch (16) and a readout (value 0). The readout attends uniformly
    (fixed logits) to every key; the value of patch j is its mean pixel times [j == TARGET]; the chunk
    (4, 7) is that readout output everywhere. So the action depends on patch TARGET alone.
    """
    frame = images["image_primary"][-1]  # (16, 16, 3)
    patches = frame.reshape(ROWS, PATCH, COLS, PATCH, 3).mean(axis=(1, 3, 4)).reshape(-1) / 255.0  # (16,)
    x = jnp.concatenate([patches, jnp.zeros(1)])  # (17,)
    n = x.shape[0]
    attention = jnp.full((n, n), 1.0 / n) + perturbation[0, 0]
    value = x * (jnp.arange(n) == TARGET)
    out = attention @ value  # (17,)
    actions = jnp.broadcast_to(100.0 * out[n - 1], (4, 7)) + jnp.linspace(0.1, 0.2, 28).reshape(4, 7)
    return actions, attention[None, None]


def toy_step(seed: int = 0) -> A.StepFunction:
    rng = np.random.default_rng(seed)
    images = {"image_primary": rng.uniform(0, 255, (1, ROWS * PATCH, COLS * PATCH, 3)).astype(np.float32)}
    fn = jax.jit(toy_fn)
    batched = jax.jit(jax.vmap(lambda imgs: toy_fn(imgs, jnp.zeros((1, 1, 17, 17)))[0]))

    def batch(imgs):
        return np.asarray(batched({k: jnp.asarray(v) for k, v in imgs.items()}))

    return A.StepFunction(fn=fn, batch=batch, images=images, tokens=toy_tokens(), shape=(1, 1, 17))


def test_saliency_and_grad_attention_rank_the_one_patch_first():
    analysis = A.analyse(toy_step(), occlusion=True)
    occlusion = A.attribute(analysis, "occlusion")["image_primary"].ravel()
    assert occlusion[TARGET] > 1e-4 and np.allclose(np.delete(occlusion, TARGET), 0.0, atol=1e-6)
    with pytest.raises(ValueError, match="occlusion needs"):
        A.attribute(A.analyse(toy_step()), "occlusion")
    for method in ("saliency", "grad-attention"):
        scores = A.attribute(analysis, method)["image_primary"]
        assert scores.shape == (ROWS, COLS)
        assert F.ranking(scores)[0] == TARGET, method
    saliency = A.attribute(analysis, "saliency")["image_primary"].ravel()
    assert saliency[TARGET] > 0 and np.allclose(np.delete(saliency, TARGET), 0.0)  # nothing else is read
    # raw attention is uniform here: it cannot tell (every patch equal), whatever the policy reads
    attention = A.attribute(analysis, "attention:0")["image_primary"]
    assert np.allclose(attention, attention.ravel()[0])


def test_gradients_agree_with_finite_differences():
    step = toy_step(seed=3)
    analysis = A.analyse(step)
    image = step.images["image_primary"]
    zeros = jnp.zeros((1, 1, 17, 17))

    def score(img):
        return float(A.direction_score(step.fn({"image_primary": jnp.asarray(img)}, zeros)[0]))

    rng = np.random.default_rng(0)
    for _ in range(5):
        idx = (0, *rng.integers(0, 16, 2), rng.integers(0, 3))
        eps = 1.0
        up, down = image.copy(), image.copy()
        up[idx] += eps
        down[idx] -= eps
        numeric = (score(up) - score(down)) / (2 * eps)
        assert analysis.grad_images["image_primary"][idx] == pytest.approx(numeric, rel=2e-2, abs=1e-7)
    # attention gradient: the readout row's entry on TARGET
    for key in (TARGET, 3):
        eps = 1e-3
        bump = np.zeros((1, 1, 17, 17), np.float32)
        bump[0, 0, 16, key] = eps
        plus = float(A.direction_score(step.fn(step.images, jnp.asarray(bump))[0]))
        minus = float(A.direction_score(step.fn(step.images, jnp.asarray(-bump))[0]))
        assert analysis.grad_attention[0, 0, 16, key] == pytest.approx((plus - minus) / (2 * eps), rel=2e-2, abs=1e-5)


@pytest.mark.slow
def test_deletion_drops_at_once_for_the_faithful_map_and_random_is_one():
    aucs, randoms, controls, groups = [], [], [], []
    for seed in range(60):
        step = toy_step(seed)
        analysis = A.analyse(step)
        maps = A.attribute_all(analysis, ("saliency", "random"), seed=seed + 1000)
        rows = F.step_faithfulness(step.batch, step.images, analysis.actions, maps, random_orders=4, seed=seed)
        by = {r["method"]: r for r in rows}
        sal = by["saliency"]
        c = sal["change_all"]
        assert c > 1e-4
        assert sal["deletion_curve"][0] == pytest.approx(0.0, abs=1e-5)
        assert sal["deletion_curve"][1] == pytest.approx(c, rel=1e-4)  # the first deleted patch moves the action fully
        assert sal["insertion_curve"][0] == pytest.approx(c, rel=1e-4) and sal["insertion_curve"][1] == pytest.approx(0, abs=1e-5)
        assert sal["deletion_auc"] == pytest.approx(c * 31 / 32, rel=1e-4)
        assert sal["insertion_auc"] == pytest.approx(c / 32, abs=1e-6)
        assert sal["top_k/1"] == pytest.approx(c, rel=1e-4)
        assert sal["bottom_k/1"] == pytest.approx(0.0, abs=1e-5)
        aucs.append(sal["deletion_auc"])
        randoms.append(by["random"]["deletion_auc"])
        controls.append(sal["random_deletion_auc"])
        groups.append(seed // 6)  # 10 "episodes" of 6 steps
    ratio, lo, hi, n = F.relative_to_random(np.array(aucs), np.array(controls), np.array(groups))
    assert ratio > 1.5 and lo > 1.4 and n == 10  # random deletion finds the patch half-way on average: AUC ~ c/2
    ratio, lo, hi, _ = F.relative_to_random(np.array(randoms), np.array(controls), np.array(groups))
    assert lo <= 1.0 <= hi, (ratio, lo, hi)


def test_camera_the_policy_ignores_has_no_curves():
    tokens = toy_tokens()
    image = np.full((16, 16, 3), 100, np.float32)
    rows = F.camera_faithfulness(lambda frames: np.zeros((len(frames), 4, 7)), image, np.zeros((4, 7)),
                                 {"m": np.arange(16.0).reshape(4, 4)})
    assert rows[0]["change_all"] == 0.0 and np.isnan(rows[0]["deletion_auc"])
    del tokens


def test_pure_helpers_known_answers():
    assert list(F.ranking(np.array([[0.1, 0.9], [0.5, 0.9]]))) == [1, 3, 2, 0]
    assert F.first_k(np.array([2, 0, 1]), [0, 2]).tolist() == [[False, False, False], [True, False, True]]
    image = np.arange(4 * 4 * 3, dtype=np.float32).reshape(4, 4, 3)
    base = F.baseline_image(image, "mean")
    assert np.allclose(base, image.mean(axis=(0, 1)))
    out = F.compose(image, base, np.array([[[True, False], [False, False]]]))[0]
    assert np.allclose(out[:2, :2], base[:2, :2]) and np.allclose(out[2:, :], image[2:, :])
    blur = F.baseline_image(image, "blur", 2, 2)
    assert blur.shape == image.shape and blur.std() < image.std()
    with pytest.raises(ValueError, match="unknown fill"):
        F.baseline_image(image, "noise")
    assert F.auc(np.array([0, 0.5, 1]), np.array([1, 0, 0])) == pytest.approx(0.25)
    assert F.action_change(np.ones((2, 3)), np.zeros((2, 3))) == pytest.approx(1.0)
    assert list(F.curve_points(4)) == [0, 1, 2, 3, 4] and F.curve_points(256)[-1] == 256
    assert F.k_values(16) == (1, 2, 4)
    # Chefer's rule on a hand-made two-layer example: R = (I + A2')(I + A1')
    a = np.array([[[[0.5, 0.5], [0.0, 1.0]]], [[[1.0, 0.0], [0.5, 0.5]]]])
    g = np.array([[[[1.0, -1.0], [1.0, 1.0]]], [[[1.0, 1.0], [2.0, 1.0]]]])
    a1 = np.clip(a[0, 0] * g[0, 0], 0, None)
    a2 = np.clip(a[1, 0] * g[1, 0], 0, None)
    expected = (np.eye(2) + a2) @ (np.eye(2) + a1)
    assert np.allclose(A.gradient_relevance(a, g), expected)


def test_parse_methods():
    assert A.parse_methods("attention,saliency", 3) == ("attention:0", "attention:1", "attention:2", "saliency", "random")
    assert A.parse_methods("attention:-1,rollout", 3) == ("attention:2", "rollout", "random")
    assert A.parse_methods("occlusion,random", 3) == ("occlusion", "random")
    with pytest.raises(ValueError, match="unknown attribution method 'lime'"):
        A.parse_methods("lime", 3)
    with pytest.raises(ValueError, match="outside the model's 3 layers"):
        A.parse_methods("attention:3", 3)


# ------------------------------------------------------------------------------- the reference policy itself

REFERENCE = __import__("pathlib").Path(__file__).resolve().parents[2] / "models" / "octo-reference-robosuite"


@pytest.fixture(scope="module")
def reference():
    from harness.octo import load_pretrained

    model = load_pretrained(str(REFERENCE))
    rng = np.random.default_rng(0)
    obs = {k: rng.integers(0, 255, (1, model.window_size, h, w, 3), dtype=np.uint8) for k, (h, w) in model.image_sizes.items()}
    obs["proprio"] = rng.standard_normal((1, model.window_size, 8)).astype(np.float32)
    obs["timestep_pad_mask"] = np.ones((1, model.window_size), bool)
    task = model.create_task(texts=["lift the red cube"])
    return model, obs, task, jax.random.PRNGKey(3)


@pytest.mark.slow
def test_octo_step_function_is_the_policy(reference):
    model, obs, task, key = reference
    actions, attention = model.sample_actions(obs, task, key, None)
    functions = A.OctoFunctions(model)
    step = functions.at(obs, task, key)
    analysis = A.analyse(step)
    np.testing.assert_allclose(analysis.actions, np.asarray(actions)[0], atol=2e-5)
    np.testing.assert_allclose(analysis.attention[:, :, attention.tokens.readout_index], np.asarray(attention.readout)[0],
                               atol=2e-5)
    batch = step.batch({k: np.repeat(v[None], 3, axis=0) for k, v in step.images.items()})
    np.testing.assert_allclose(batch, np.repeat(analysis.actions[None], 3, axis=0), atol=2e-5)
    # the image gradient along its own direction agrees with a finite difference of S
    direction = {k: v / np.linalg.norm(v) for k, v in analysis.grad_images.items()}
    zeros = jnp.zeros((functions.layers, functions.heads, step.tokens.num_keys, step.tokens.num_keys))
    eps = 0.5
    shifted = lambda s: float(A.direction_score(step.fn(  # noqa: E731
        {k: jnp.asarray(step.images[k] + s * eps * direction[k]) for k in step.images}, zeros)[0]))
    numeric = (shifted(1) - shifted(-1)) / (2 * eps)
    analytic = sum(float((analysis.grad_images[k] * direction[k]).sum()) for k in step.images)
    assert numeric == pytest.approx(analytic, rel=0.05)
    for method in A.parse_methods("attention,rollout,grad-attention,saliency", functions.layers):
        maps = A.attribute(analysis, method)
        assert set(maps) == set(model.image_sizes)
        grids = {key: (rows, cols) for _, key, rows, cols in step.tokens.image_groups}
        assert all(m.shape == grids[k] and np.isfinite(m).all() for k, m in maps.items())


@pytest.mark.slow
def test_the_diffusion_head_is_differentiated_with_the_steps_rng(fixtures_dir):
    from harness.octo import load_pretrained

    model = load_pretrained(str(fixtures_dir / "tiny"))  # a DiffusionHead checkpoint of the original code
    rng = np.random.default_rng(1)
    obs = {k: rng.integers(0, 255, (1, model.window_size, h, w, 3), dtype=np.uint8) for k, (h, w) in model.image_sizes.items()}
    obs["timestep_pad_mask"] = np.ones((1, model.window_size), bool)
    task = model.create_task(texts=["pick up the cube"])
    key = jax.random.PRNGKey(5)
    actions, _ = model.sample_actions(obs, task, key[None], None)  # a per-example key: what a run uses
    functions = A.OctoFunctions(model)
    step = functions.at(obs, task, key)
    analysis = A.analyse(step)
    np.testing.assert_allclose(analysis.actions, np.asarray(actions)[0], atol=2e-5)
    direction = {k: v / np.linalg.norm(v) for k, v in analysis.grad_images.items()}
    zeros = jnp.zeros((functions.layers, functions.heads, step.tokens.num_keys, step.tokens.num_keys))
    eps = 0.5
    shifted = lambda s: float(A.direction_score(step.fn(  # noqa: E731
        {k: jnp.asarray(step.images[k] + s * eps * direction[k]) for k in step.images}, zeros)[0]))
    analytic = sum(float((analysis.grad_images[k] * direction[k]).sum()) for k in step.images)
    assert analytic > 0 and (shifted(1) - shifted(-1)) / (2 * eps) == pytest.approx(analytic, rel=0.05)

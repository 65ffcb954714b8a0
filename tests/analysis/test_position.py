"""Position against content (harness/analysis/position.py and --attention-controls): the flag rule on hand-made
maps, and known answers on models made by editing the committed reference policy's parameters:

- a fixed bias on one primary image token's layer-0 attention logit (its position embedding pinned to a direction
  the readout's layer-0 query favours in every head, large enough that the token's LayerNorm output no longer
  depends on the pixels) gets that patch flagged, and no other, in every head and the head mean, whatever the pixels;
- a model whose primary-camera attention follows content (position embeddings and projection bias of the primary
  camera zeroed, layer-0 queries sharpened) looks at a bright square, sees it move to the mirror-image patch under
  the mirror, and gets nothing flagged;
- mirroring twice gives the recorded attention back bit for bit, and the controls do not change the actions.
"""

import copy
from pathlib import Path

import jax
import numpy as np
import pytest

from harness.policies import as_policy
from harness.analysis import position as Q
from harness.measures import controls as C
from harness.measures.attention import camera_maps
from harness.octo import load_pretrained
from harness.policy import InferenceRequest, PolicyConfig, TaskPrompt, window_from_entries

MODEL = Path(__file__).resolve().parents[2] / "models" / "octo-reference-robosuite"
KEYS = ["image_primary", "image_wrist", "proprio"]


# ---- pure functions on hand-made inputs ----------------------------------------------------------------------------


def test_blank_and_mirror_frames():
    frames = np.arange(2 * 4 * 6 * 3, dtype=np.uint8).reshape(2, 4, 6, 3)
    mirrored = C.mirror_frames(frames)
    assert np.array_equal(mirrored[:, :, 0], frames[:, :, -1])
    assert np.array_equal(C.mirror_frames(mirrored), frames)
    blank = C.blank_frames(frames)
    assert blank.shape == frames.shape and blank.dtype == np.uint8
    for i in range(2):  # each frame its own mean colour
        expected = np.rint(frames[i].reshape(-1, 3).mean(axis=0))
        assert np.array_equal(blank[i, 1, 2], expected) and np.ptp(blank[i].reshape(-1, 3), axis=0).max() == 0


def test_parse_controls():
    assert C.parse_controls("mirror,blank") == ("blank", "mirror")
    for bad in ("", "blank,", "blur", None):
        with pytest.raises(ValueError, match="attention-controls"):
            C.parse_controls(bad)


def test_flag_rule_on_hand_made_maps():
    real = np.full((4, 4), 1.0)
    real[0, 0] = 10.0  # hot and position-bound
    real[1, 1] = 10.0  # hot but gone on the blank frame (content)
    real[2, 2] = 10.0  # hot, remains blank, but moves under the mirror (content that the mirror moves)
    blank = np.full((4, 4), 1.0)
    blank[0, 0], blank[2, 2] = 8.0, 9.0
    mirrored = np.full((4, 4), 1.0)
    mirrored[0, 0], mirrored[1, 1] = 6.0, 10.0
    flags = Q.flag_position_bound(real, blank, mirrored)
    assert flags.sum() == 1 and flags[0, 0]
    # not hot: a uniform map flags nothing even when it stays put
    assert not Q.flag_position_bound(np.ones((4, 4)), np.ones((4, 4)), np.ones((4, 4))).any()
    assert Q.remaining_share(real, blank) == pytest.approx((8 + 1 + 9 + 13) / (30 + 13))
    assert Q.flagged_share(real, flags) == pytest.approx(10 / 43)


def test_content_only_view():
    real = np.array([[4.0, 1.0], [1.0, 2.0]])
    blank = np.array([[1.0, 1.0], [2.0, 1.0]])
    view = Q.content_only(real, blank)
    assert view.sum() == pytest.approx(real.sum())  # renormalised to the real map's mass
    assert np.allclose(view, np.array([[3.0, 0.0], [0.0, 1.0]]) * 2.0)
    assert not Q.content_only(np.ones((2, 2)), np.ones((2, 2))).any()  # nothing left: all zero, no nan
    fraction = np.array([[1.0, 0.0], [0.0, 0.0]])  # a mask covering patch (0, 0): area 1/4
    assert Q.mask_lift(real, fraction) == pytest.approx((4 / 8) / 0.25)
    assert np.isnan(Q.mask_lift(real, np.zeros((2, 2))))


def test_patch_means_reads_the_mirror_image_patch():
    real = np.zeros((1, 1, 1, 2, 4))
    real[..., 0, 1] = 1.0
    mirror = np.zeros_like(real)
    mirror[..., 0, 2] = 1.0  # content at column 1 moved to column 4-1-1 = 2
    means = Q.patch_means(real, real, mirror)
    assert means.real.shape == (1, 2, 2, 4)  # head mean appended
    assert means.followed[0, 0, 0, 1] == 1.0 and means.mirrored[0, 0, 0, 1] == 0.0
    with pytest.raises(ValueError, match="one shape"):
        Q.patch_means(real, real, mirror[..., :2])


def test_policy_config_controls_options():
    assert PolicyConfig(attention_controls="mirror,blank").controls_every == 1
    assert PolicyConfig(attention_controls="blank", controls_every=5).to_dict()["attention_controls"] == "blank"
    plain = PolicyConfig().to_dict()
    assert "attention_controls" not in plain and "controls_every" not in plain  # protocols without keep their hash
    with pytest.raises(ValueError, match="needs --attention-controls"):
        PolicyConfig(controls_every=3)
    with pytest.raises(ValueError, match="controls-every"):
        PolicyConfig(attention_controls="blank", controls_every=-1)
    with pytest.raises(ValueError, match="unknown control"):
        PolicyConfig(attention_controls="blank,noise")


# ---- known answers on edited models --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def model():
    return load_pretrained(str(MODEL))


def _edited(model, edit):
    """A shallow copy of `model` whose backbone parameters went through `edit(backbone)` (numpy copies)."""
    params = jax.tree.map(lambda x: np.array(x), model._inference_params)
    edit(params["octo_transformer"])
    out = copy.copy(model)
    out._inference_params = params
    return out


def _layer0(backbone):
    return backbone["BlockTransformer_0"]["Transformer_0"]["encoderblock_0"]


def bias_model(model, patch: int):
    """Primary token `patch`'s layer-0 key is pinned so that the readout's layer-0 logit on it is several units
    higher than any pixels could make it, in every head: its position embedding is a huge vector w (1e4 x unit
    scale) along the direction that raises every head's logit (least squares through LayerNorm_0's scale), so
    LayerNorm_0 of the token is scale * w_hat + bias whatever the projected pixels add."""

    def edit(b):
        block = _layer0(b)
        norm, attention = block["LayerNorm_0"], block["MultiHeadDotProductAttention_0"]
        readout = b["readout_action_pos_embedding"][0, 0, 0]  # the readout's layer-0 input (no content)
        x = (readout - readout.mean()) / np.sqrt(readout.var() + 1e-6) * norm["scale"] + norm["bias"]
        query = np.einsum("d,dhk->hk", x, attention["query"]["kernel"]) + attention["query"]["bias"]  # (heads, hd)
        gradient = np.einsum("dhk,hk->hd", attention["key"]["kernel"], query) * norm["scale"][None]  # (heads, D)
        w = np.linalg.lstsq(gradient, np.ones(len(gradient)), rcond=None)[0]
        w -= w.mean()
        w *= np.sqrt(len(w)) / np.linalg.norm(w)  # what LayerNorm makes of it
        gain = gradient @ w / np.sqrt(query.shape[1])
        assert gain.min() > 3.0, f"the pinned token's logit gain per head {gain} is too small to dominate"
        b["obs_primary_pos_embedding"][0, :, patch, :] = 1e4 * w

    return _edited(model, edit)


def content_model(model):
    """The primary camera's tokens carry content only (position embeddings and projection bias zeroed) and the
    layer-0 queries are 4x sharper, so layer-0 attention follows what is in the frame."""

    def edit(b):
        b["obs_primary_pos_embedding"][...] = 0.0
        b["obs_primary_projection"]["bias"][...] = 0.0
        attention = _layer0(b)["MultiHeadDotProductAttention_0"]
        attention["query"]["kernel"] *= 4.0
        attention["query"]["bias"] *= 4.0

    return _edited(model, edit)


def _request(frame_primary, frame_wrist, window: int, step: int = 0) -> InferenceRequest:
    entry = {"image_primary": frame_primary, "image_wrist": frame_wrist, "proprio": np.zeros(8, np.float32)}
    return InferenceRequest(window_from_entries([entry], window, KEYS), TaskPrompt.of("pick up the red cube"), 7, step)


def _infer(model, request, controls="blank,mirror"):
    config = PolicyConfig(attention_controls=controls, dataset_key="robosuite_reference")
    inference = as_policy(model).inference(config)
    (result,) = inference([request])
    return inference, result


def _flags(result, layer: int = 0):
    """(heads + 1, rows, cols) flags and PatchMeans of the primary camera at `layer` from one control step."""
    maps = [camera_maps(x, result.tokens, "image_primary").mean(axis=2)[None]
            for x in (result.readout_attention, result.probes["controls"]["blank"], result.probes["controls"]["mirror"])]
    means = Q.patch_means(*maps)
    return Q.flag_position_bound(means.real, means.blank, means.mirrored)[layer], means


def _noise(seed, size):
    return np.random.default_rng(seed).integers(0, 256, (size, size, 3), dtype=np.uint8)


@pytest.mark.slow
def test_a_fixed_bias_on_one_token_gets_that_patch_flagged_and_no_other(model):
    patch = 19  # row 2, col 3 of the 8x8 primary grid
    biased = bias_model(model, patch)
    for seed in (0, 1):  # whatever the pixels
        _, result = _infer(biased, _request(_noise(seed, 128), _noise(seed + 10, 64), model.window_size))
        flags, means = _flags(result)
        for head in range(flags.shape[0]):  # every head and the head mean (last)
            assert np.argwhere(flags[head]).tolist() == [[2, 3]], (seed, head)
        assert means.real[0, -1, 2, 3] > 0.5 * means.real[0, -1].sum()
    # the unedited model does not flag that patch on the same frames: the flag is the edit's doing
    _, plain = _infer(model, _request(_noise(0, 128), _noise(10, 64), model.window_size))
    assert not _flags(plain)[0][-1, 2, 3]


def _square(row, col, size=128, grid=8):
    frame = np.full((size, size, 3), 40, np.uint8)
    cell = size // grid
    frame[row * cell:(row + 1) * cell, col * cell:(col + 1) * cell] = 240
    return frame


def test_attention_that_follows_a_bright_square_moves_under_the_mirror_and_nothing_is_flagged(model):
    following = content_model(model)
    wrist = np.full((64, 64, 3), 40, np.uint8)
    for row, col in ((2, 1), (5, 2)):
        _, result = _infer(following, _request(_square(row, col), wrist, model.window_size))
        flags, means = _flags(result)
        real, mirrored = means.real[0, -1], means.mirrored[0, -1]
        hot = np.unravel_index(real.argmax(), real.shape)
        assert abs(hot[0] - row) <= 1 and abs(hot[1] - col) <= 1  # it looks at the square (its patch or an edge)
        assert real.max() > 4 * real.mean()
        moved = np.unravel_index(mirrored.argmax(), mirrored.shape)
        assert moved == (hot[0], real.shape[1] - 1 - hot[1])  # the mirror moves it to the mirror-image patch
        assert means.blank[0, -1][hot] < Q.KEEP * real[hot]  # no square on the blank frame, no attention there
        assert not flags.any(), np.argwhere(flags).tolist()


def test_mirroring_twice_gives_the_recorded_attention_back_bit_for_bit(model):
    request = _request(_noise(3, 128), _noise(4, 64), model.window_size)
    inference, result = _infer(model, request)
    controls = inference.probe("controls")
    twice = controls.attention([request], inference.context, {"twice": lambda x: C.mirror_frames(C.mirror_frames(x))})["twice"]
    assert np.array_equal(twice[0], result.readout_attention)
    once = controls.attention([request], inference.context, {"mirror": C.mirror_frames})["mirror"]
    assert np.array_equal(once[0], result.probes["controls"]["mirror"])  # the stored control is that pass
    assert not np.array_equal(result.probes["controls"]["mirror"], result.readout_attention)
    # float16, as controls.npz and attention.npz store them: still bit for bit
    assert np.array_equal(twice[0].astype(np.float16), result.readout_attention.astype(np.float16))


def test_controls_do_not_change_the_actions_and_run_only_on_their_steps(model):
    config = PolicyConfig(dataset_key="robosuite_reference")
    (plain,) = as_policy(model).inference(config)([_request(_noise(5, 128), _noise(6, 64), model.window_size, step=3)])
    every2 = PolicyConfig(attention_controls="blank,mirror", controls_every=2, dataset_key="robosuite_reference")
    inference = as_policy(model).inference(every2)
    (odd,) = inference([_request(_noise(5, 128), _noise(6, 64), model.window_size, step=3)])
    (even,) = inference([_request(_noise(5, 128), _noise(6, 64), model.window_size, step=4)])
    assert np.array_equal(plain.chunk, odd.chunk) and np.array_equal(plain.readout_attention, odd.readout_attention)
    assert "controls" not in odd.probes and set(even.probes["controls"]) == {"blank", "mirror"}
    assert even.probes["controls"]["blank"].shape == even.readout_attention.shape

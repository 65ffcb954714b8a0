"""Episode writers on synthetic episodes (tiny layout): files, round trips, abort and error paths; video sinks."""

import json
import threading

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from harness.octo.tokens import TokenMap, build_token_map
from harness.records import EpisodeMeta, StepRecord
from harness.outputs.video import GifWriter, Mp4Writer
from harness.outputs.writers import EpisodeWriter, OutputOptions, WriterError

LAYERS, HEADS, KEYS = 2, 4, 90

# imageio's ffmpeg *reader* (used here to decode and count frames) leaves its pipes to the garbage collector
pytestmark = [
    pytest.mark.filterwarnings("ignore::ResourceWarning"),
    pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning"),
]


def tiny_tokens():
    return build_token_map(
        [("task_language", 16)],
        [("obs_primary", 16), ("obs_wrist", 4), ("obs_task_language", 16), ("readout_action", 1)],
        2,
        (("obs_primary", "image_primary", 4, 4), ("obs_wrist", "image_wrist", 2, 2)),
    )


def meta(**kw):
    base = dict(
        run="test", task="Lift", episode=0, seed=7, instruction="pick up the red cube", model="random:tiny",
        model_is_random=True, dataset_key=None, text_tokenizer="fallback", execution="temporal_ensemble",
    )
    return EpisodeMeta(**{**base, **kw})


def records(n=3, seed=0, full=False, keys=KEYS):
    rng = np.random.default_rng(seed)
    target = np.zeros((128, 128), bool)
    target[32:64, 64:96] = True  # camera-resolution mask; frames the model saw are 64 px
    out = []
    for t in range(n):
        out.append(
            StepRecord(
                step=t,
                frames={
                    "image_primary": rng.integers(0, 256, (64, 64, 3), dtype=np.uint8),
                    "image_wrist": rng.integers(0, 256, (32, 32, 3), dtype=np.uint8),
                },
                readout_attention=rng.dirichlet(np.ones(keys), size=(LAYERS, HEADS, 1)).astype(np.float32),
                actions_predicted=rng.normal(size=(4, 7)).astype(np.float32),
                action_executed=rng.normal(size=7).astype(np.float32),
                reward=float(t == n - 1),
                success=t == n - 1,
                masks={"image_primary": {"target": target, "robot": ~target}},
                full_attention=rng.dirichlet(np.ones(keys), size=(LAYERS, HEADS, keys)).astype(np.float32) if full else None,
                timings={"simulation": 0.01, "inference": 0.02},
            )
        )
    return out


def no_temps(path):
    return not [p.name for p in path.iterdir() if ".tmp" in p.name]


def test_episode_writer_writes_all_outputs(tmp_path):
    tokens = tiny_tokens()
    recs = records(3)
    writer = EpisodeWriter(tmp_path / "ep", tokens, meta(), OutputOptions(fps=5))
    for r in recs:
        assert writer.add_step(r) >= 0.0
    summary = writer.finish({"note": "from the runner", "timings": {"step": 0.5}})
    ep = tmp_path / "ep"

    pngs = sorted(p.name for p in ep.glob("*.png"))
    assert pngs == [f"step_{t:04d}_layer_{layer:02d}.png" for t in range(3) for layer in range(LAYERS)]
    with Image.open(ep / pngs[0]) as im:
        assert im.mode == "RGB" and im.width > 5 * 128  # 4 heads + mean, frames shown at >= 128 px

    frames = list(iio.imiter(ep / "rollout.mp4"))
    assert len(frames) == 3
    assert len({f.shape for f in frames}) == 1 and frames[0].shape[0] % 16 == 0 and frames[0].shape[1] % 16 == 0

    with np.load(ep / "attention.npz") as z:
        attn = z["readout_attention"]
        assert attn.dtype == np.float16 and attn.shape == (3, LAYERS, HEADS, 1, KEYS)
        np.testing.assert_allclose(attn[1], recs[1].readout_attention, atol=1e-3)
        back = TokenMap.from_arrays(z)
        for field in ("group", "timestep", "row", "col", "readout_index"):
            np.testing.assert_array_equal(getattr(back, field), getattr(tokens, field))
        assert back.image_groups == tokens.image_groups
        assert z["metrics/share/primary"].shape == (3, LAYERS)
        shares = sum(z[f"metrics/share/{k}"] for k in ("primary", "wrist", "language", "readout"))
        np.testing.assert_allclose(shares, 1.0, atol=1e-5)
        assert z["metrics/mask_mass/image_primary/target"].shape == (3, LAYERS)
        np.testing.assert_allclose(z["metrics/mask_area/image_primary/target"], 1 / 16)
        np.testing.assert_array_equal(z["step"], [0, 1, 2])
    with np.load(ep / "actions.npz") as z:
        assert z["predicted"].shape == (3, 4, 7) and z["executed"].shape == (3, 7)
        np.testing.assert_array_equal(z["executed"][2], recs[2].action_executed)
        np.testing.assert_array_equal(z["success"], [False, False, True])

    lines = (ep / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == 3
    first = json.loads(lines[0])
    assert first["step"] == 0 and len(first["share"]["primary"]) == LAYERS and len(first["entropy"]) == LAYERS
    assert set(first["mask_mass"]["image_primary"]) == {"target", "robot"}
    assert {"simulation", "inference", "write", "blocked"} <= set(first["timings"])

    info = json.loads((ep / "episode.json").read_text())
    for key, value in dict(seed=7, task="Lift", instruction="pick up the red cube", model="random:tiny",
                           model_is_random=True, success=True, steps=3, note="from the runner").items():
        assert info[key] == value, key
    assert info["files"]["video"] == "rollout.mp4" and info["files"]["png_count"] == 6
    assert info["timings"]["total"]["inference"] == pytest.approx(0.06) and info["timings"]["step"] == 0.5
    assert summary["paths"]["attention"] == str(ep / "attention.npz")
    assert no_temps(ep)
    assert len(writer.blocked_seconds) == 3


def test_options_select_steps_layers_and_episode_normalisation(tmp_path):
    opts = OutputOptions(png_every=2, layers=(-1,), video=False, gif=True, gif_every=1, normalisation="episode")
    writer = EpisodeWriter(tmp_path, tiny_tokens(), meta(), opts)
    for r in records(3):
        writer.add_step(r)
    summary = writer.finish()
    assert sorted(p.name for p in tmp_path.glob("*.png")) == ["step_0000_layer_01.png", "step_0002_layer_01.png"]
    assert not (tmp_path / "rollout.mp4").exists()
    assert iio.imread(tmp_path / "rollout.gif").shape[0] == 3
    assert summary["files"]["png_count"] == 2 and "video" not in summary["files"]
    assert no_temps(tmp_path)


def test_rollout_video_stores_rollout_rows(tmp_path):
    writer = EpisodeWriter(tmp_path, tiny_tokens(), meta(), OutputOptions(png_every=0, video_attention="rollout"))
    for r in records(2, full=True):
        writer.add_step(r)
    writer.finish()
    with np.load(tmp_path / "attention.npz") as z:
        assert z["rollout_readout"].shape == (2, 1, KEYS)
        np.testing.assert_allclose(z["rollout_readout"].astype(np.float32).sum(-1), 1.0, atol=1e-2)
    assert len(list(iio.imiter(tmp_path / "rollout.mp4"))) == 2
    assert not list(tmp_path.glob("*.png"))


def test_abort_leaves_no_temporaries_and_no_episode_json(tmp_path):
    (tmp_path / "episode.json").write_text("{}")  # stale, from an earlier run
    writer = EpisodeWriter(tmp_path, tiny_tokens(), meta(), OutputOptions())
    assert not (tmp_path / "episode.json").exists()
    for r in records(3):
        writer.add_step(r)
    writer.abort()
    assert no_temps(tmp_path)
    assert not (tmp_path / "episode.json").exists() and not (tmp_path / "rollout.mp4").exists()
    with pytest.raises(RuntimeError, match="finished or aborted"):
        writer.add_step(records(1)[0])


def test_context_manager_aborts_on_exception(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with EpisodeWriter(tmp_path, tiny_tokens(), meta(), OutputOptions()) as writer:
            writer.add_step(records(1)[0])
            raise KeyboardInterrupt
    assert no_temps(tmp_path) and not (tmp_path / "episode.json").exists()


def test_exception_in_writer_thread_surfaces(tmp_path):
    good, bad = records(1)[0], records(1, keys=KEYS - 1)[0]
    writer = EpisodeWriter(tmp_path / "a", tiny_tokens(), meta(), OutputOptions())
    writer.add_step(good)
    writer.add_step(bad)
    writer._thread.join(timeout=30)  # the thread stops at the bad step
    with pytest.raises(WriterError, match="step 0.*keys=90") as info:
        writer.add_step(good)
    assert isinstance(info.value.__cause__, ValueError)
    writer.abort()

    writer = EpisodeWriter(tmp_path / "b", tiny_tokens(), meta(), OutputOptions(layers=(5,)))
    writer.add_step(good)
    with pytest.raises(WriterError, match="out of range"):
        writer.finish()
    assert no_temps(tmp_path / "b") and not (tmp_path / "b" / "episode.json").exists()


def test_add_step_blocks_when_the_writer_falls_behind(tmp_path):
    writer = EpisodeWriter(tmp_path, tiny_tokens(), meta(), OutputOptions(queue_size=1, png_every=0, video=False))
    gate = threading.Event()
    process = writer._process
    writer._process = lambda record: (gate.wait(), process(record))  # hold the thread on the first step
    recs = records(3)
    writer.add_step(recs[0])
    threading.Timer(0.3, gate.set).start()
    writer.add_step(recs[1])  # fills the queue
    blocked = writer.add_step(recs[2])  # must wait until the gate opens
    assert blocked > 0.1
    assert writer.finish()["steps"] == 3


def test_options_validation():
    with pytest.raises(ValueError, match="normalisation"):
        OutputOptions(normalisation="global")
    with pytest.raises(ValueError, match="video_attention"):
        OutputOptions(video_attention="last")
    with pytest.raises(ValueError, match="colormap"):
        OutputOptions(cmap="nope")
    with pytest.raises(ValueError, match="png_every"):
        OutputOptions(png_every=-1)


def test_mp4_writer_frame_count_and_size(tmp_path):
    path = tmp_path / "v.mp4"
    rng = np.random.default_rng(0)
    with Mp4Writer(path, fps=10) as writer:
        for _ in range(7):
            writer.append(rng.integers(0, 256, (96, 160, 3), dtype=np.uint8))
    frames = list(iio.imiter(path))
    assert len(frames) == 7 and frames[0].shape == (96, 160, 3)
    assert no_temps(tmp_path)

    odd = Mp4Writer(tmp_path / "odd.mp4")
    odd.append(np.zeros((50, 70, 3), np.uint8))  # padded to 64x80, never resampled
    with pytest.raises(ValueError, match="size changed"):
        odd.append(np.zeros((52, 70, 3), np.uint8))
    odd.close()
    assert iio.imread(tmp_path / "odd.mp4", index=0).shape == (64, 80, 3)

    aborted = Mp4Writer(tmp_path / "gone.mp4")
    aborted.append(np.zeros((32, 32, 3), np.uint8))
    aborted.abort()
    assert not list(tmp_path.glob("gone*"))


def test_mp4_writer_reports_ffmpeg_failure(tmp_path):
    writer = Mp4Writer(tmp_path / "bad.mp4", preset="no-such-preset")
    with pytest.raises(RuntimeError, match="ffmpeg"):
        for _ in range(50):  # ffmpeg exits at start-up; a write or close notices
            writer.append(np.zeros((64, 64, 3), np.uint8))
        writer.close()
    writer.abort()
    assert not list(tmp_path.iterdir())


def test_gif_writer_thins_and_shrinks(tmp_path):
    gif = GifWriter(tmp_path / "a.gif", fps=10, every=2, shrink=2)
    for i in range(5):
        gif.append(np.full((32, 48, 3), i * 40, np.uint8))
    gif.close()
    frames = iio.imread(tmp_path / "a.gif")
    assert frames.shape[:3] == (3, 16, 24)


def test_encode_png_round_trips_through_pillow():
    rng = np.random.default_rng(4)
    image = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    image[10:20] = 200  # flat area next to noise: exercises the Up filter's wraparound both ways
    import io

    from harness.outputs.panels import encode_png

    for level in (0, 2, 9):
        with Image.open(io.BytesIO(encode_png(image, level))) as im:
            assert im.mode == "RGB"
            np.testing.assert_array_equal(np.asarray(im), image)

"""The reliance map as a layer over each camera of the Rerun recording (issue 45, item 4): the map of hand-made masks
and rows has the expected value on every pixel; the recording sink logs it at reliance steps only (an unused camera
gets an empty layer, a camera without masks none) with the values reliance.jsonl stores; reliance.jsonl is read back
by step for `view`, refusing a row of the wrong types; and a real short run (tiny fixture model, Lift, 3 steps,
--reliance-every 2, masks on, --rerun save) holds the layer at steps 0 and 2, tied to its reliance.jsonl, and
`view`'s rebuild from the run's files gives the same entities, layers and reliance scalars (without re-simulation:
the scalars, no layer), read back with Rerun's own loader."""

from __future__ import annotations

import io
import json
import shutil

import numpy as np
import pytest
import rerun as rr
from PIL import Image

from harness.probes.reliance.reader import rows_by_step
from harness.outputs.overlays import colormap_lut
from harness.probes.reliance.viewer import LAYER_ALPHA, layer_png, reliance_map
from harness.outputs.rerun_sink import RRD_NAME, RerunRecording
from harness.outputs.writers import OutputOptions
from tests.outputs.test_sinks import STEPS, drive, with_extras
from tests.outputs.test_writers import records

TOP = round(255 * LAYER_ALPHA)  # the alpha of the map's maximum


def _masks() -> dict[str, np.ndarray]:
    """128 px camera masks: target and gripper boxes, the background the rest (no remainder)."""
    target = np.zeros((128, 128), bool)
    target[32:64, 64:96] = True
    gripper = np.zeros((128, 128), bool)
    gripper[96:112, 0:32] = True
    return {"target": target, "gripper": gripper, "background": ~(target | gripper)}


def _row(region: str, per_pixel: float | None, share: float | None, camera: str = "image_primary", step: int = 0):
    return {"step": step, "camera": camera, "region": region, "fill": "mean", "change": 0.1, "area_fraction": 0.25,
            "reliance_per_pixel": per_pixel, "reliance_share": share, "camera_change": 0.3}


def _rgba(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGBA"))


# ---------------------------------------------------------------------------------------------- hand-made


def test_a_region_with_reliance_share_one_is_the_only_nonzero_region():
    rows = [_row("target", 16.0, 1.0), _row("gripper", 0.0, 0.0), _row("background", 0.0, 0.0)]
    values = reliance_map(_masks(), rows, (64, 64))  # the 128 px masks on a 64 px frame: pixel centres 1, 3, 5, ...
    expected = np.zeros((64, 64), np.float32)
    expected[16:32, 32:48] = 16.0
    np.testing.assert_array_equal(values, expected)
    rgba = _rgba(layer_png(values))
    assert rgba.shape == (64, 64, 4)
    assert np.array_equal(rgba[..., 3] > 0, expected > 0)  # transparent wherever the policy does not rely
    assert (rgba[16:32, 32:48, 3] == TOP).all() and (rgba[16:32, 32:48, :3] == colormap_lut("viridis")[255]).all()


def test_each_pixel_gets_its_regions_reliance_per_pixel_and_an_unused_camera_none():
    rows = [_row("target", 2.0, 0.5), _row("gripper", 0.0, 0.0), _row("background", 0.5, 0.5)]
    values = reliance_map(_masks(), rows, (128, 128))
    masks = _masks()
    assert (values[masks["target"]] == 2.0).all() and (values[masks["gripper"]] == 0.0).all()
    assert (values[masks["background"]] == 0.5).all()
    alpha = _rgba(layer_png(values))[..., 3]
    assert set(np.unique(alpha[masks["background"]])) == {round(255 * LAYER_ALPHA * 0.25)}  # a quarter of the maximum
    # a camera the policy did not use at the step (shares null): nothing relied on, an empty layer
    unused = [_row("target", 2.0, None), _row("background", 0.5, None)]
    assert not reliance_map(_masks(), unused, (64, 64)).any()
    assert not _rgba(layer_png(reliance_map(_masks(), unused, (64, 64))))[..., 3].any()
    assert not reliance_map(_masks(), [], (64, 64)).any()


def _blobs(path, entity: str) -> tuple[list[int], list[bytes]]:
    rec = rr.dataframe.load_recording(str(path))
    table = rec.view(index="step", contents=entity).select(columns=["step", f"{entity}:Blob"]).read_all()
    pairs = [(s, bytes(c[0])) for s, c in zip(table.column("step").to_pylist(), table.column(f"{entity}:Blob").to_pylist())
             if c is not None]
    return [s for s, _ in pairs], [b for _, b in pairs]


def _scalars(path, entity: str) -> tuple[list[int], list[float]]:
    rec = rr.dataframe.load_recording(str(path))
    table = rec.view(index="step", contents=entity).select(columns=["step", f"{entity}:Scalar"]).read_all()
    pairs = [(s, v[0]) for s, v in zip(table.column("step").to_pylist(), table.column(f"{entity}:Scalar").to_pylist())
             if v is not None]
    return [s for s, _ in pairs], [v for _, v in pairs]


def _entities(path) -> set[str]:
    rec = rr.dataframe.load_recording(str(path))
    return {c.entity_path for c in rec.schema().component_columns() if not c.entity_path.startswith("/__")}


def test_the_sink_logs_the_layer_at_reliance_steps_only_with_the_stored_values(tmp_path):
    """The writer's records: image_primary has masks (target, robot = the rest) on a 64 px frame; image_wrist none."""
    assert STEPS >= 3
    relied = [_row("target", 1 / 0.0625, 0.123456789), _row("robot", 0.0, 0.0),
              _row("target", 1.0, 1.0, camera="image_wrist")]  # the wrist camera has no masks: no layer
    unused = [_row("target", 3.0, None, step=2), _row("robot", 1.0, None, step=2)]
    recs = with_extras(records(STEPS), reliance={0: {"rows": relied, "seconds": 0.1}, 2: {"rows": unused, "seconds": 0.1}})
    drive(RerunRecording, tmp_path, recs, options=OutputOptions(rerun=True, png_every=0, video=False))
    rrd = tmp_path / RRD_NAME
    entities = _entities(rrd)
    assert "/camera/image_primary/reliance" in entities and "/camera/image_wrist/reliance" not in entities
    steps, blobs = _blobs(rrd, "/camera/image_primary/reliance")
    assert steps == [0, 2]  # step 1 shows step 0's map (latest-at)
    expected = np.zeros((64, 64), np.float32)
    expected[16:32, 32:48] = 16.0  # the target mask [32:64, 64:96] of the 128 px camera on the 64 px frame
    assert blobs[0] == layer_png(expected)
    assert not _rgba(blobs[1])[..., 3].any()  # step 2: the camera not used; the layer empties, step 0's does not stay
    # the scalar as reliance.jsonl stores it (6 significant digits), so a rebuild from the file logs the same value
    assert _scalars(rrd, "/reliance/image_primary/target") == ([0], [0.123457])
    # without reliance rows no layer and no reliance entity at all
    drive(RerunRecording, tmp_path / "plain", records(STEPS), options=OutputOptions(rerun=True, png_every=0, video=False))
    assert not [e for e in _entities(tmp_path / "plain" / RRD_NAME) if "reliance" in e]


def test_reliance_jsonl_is_read_back_by_step_and_a_wrong_row_is_one_line(tmp_path):
    assert rows_by_step(tmp_path) == {}
    rows = [_row("target", 2.0, 0.5), _row("background", 0.5, 0.5), _row("target", 1.0, None, step=2)]
    (tmp_path / "reliance.jsonl").write_text("".join(json.dumps({"run": "r", **row}) + "\n" for row in rows))
    by_step = rows_by_step(tmp_path)
    assert sorted(by_step) == [0, 2] and [r["region"] for r in by_step[0]["rows"]] == ["target", "background"]
    assert by_step[2]["rows"][0]["reliance_share"] is None
    for field, value in (("reliance_share", "x"), ("reliance_per_pixel", [1]), ("step", True), ("camera", 3)):
        bad = dict(rows[0], **{field: value})
        (tmp_path / "reliance.jsonl").write_text(json.dumps(bad) + "\n")
        with pytest.raises(ValueError) as error:
            rows_by_step(tmp_path)
        message = str(error.value)
        assert "\n" not in message and "reliance.jsonl row 1" in message and field in message


# ---------------------------------------------------------------------------------------------- a real run

CAMERAS = (("image_primary", "agentview", 64), ("image_wrist", "robot0_eye_in_hand", 32))  # the tiny model's sizes


@pytest.mark.slow
def test_a_run_holds_the_layer_at_reliance_steps_and_view_rebuilds_it(fixtures_dir, tmp_path):
    import envs
    from harness.octo import load_pretrained
    from harness.policy import PolicyConfig
    from harness.run import execute
    from harness.run.protocol import Protocol
    from harness.gate.view import build_recording

    model = load_pretrained(str(fixtures_dir / "tiny"))
    protocol = Protocol(model=model.source, tasks=("Lift",), episodes=1, seed=5, max_steps=3,
                        env=envs.EnvOptions(masks=True, fast_render=True, cameras=CAMERAS),
                        policy=PolicyConfig(reliance_every=2, reliance_fill="mean"),
                        outputs=OutputOptions(png_every=0, video=False, rerun=True))
    summary = execute(protocol, tmp_path, "live", model=model, progress=False)
    assert [r.status for r in summary.rows] == ["ok"]
    episode = summary.episode_dir(summary.rows[0])
    live = episode / RRD_NAME
    rows = [json.loads(line) for line in (episode / "reliance.jsonl").read_text().splitlines()]
    layers = {f"/camera/{cam}/reliance" for cam, _, _ in CAMERAS}
    assert layers <= _entities(live)
    for cam, _, size in CAMERAS:
        steps, blobs = _blobs(live, f"/camera/{cam}/reliance")
        assert steps == [0, 2]  # the reliance steps of 3 with --reliance-every 2, and only those
        for step, blob in zip(steps, blobs):
            alpha = _rgba(blob)[..., 3]
            assert alpha.shape == (size, size)  # the frame the model saw (the cameras render at the model's sizes)
            mine = [r for r in rows if r["step"] == step and r["camera"] == cam]
            if any(r["reliance_share"] is None for r in mine):
                assert not alpha.any()
                continue
            # each region covers its area fraction of the frame at its level of the map (frames upright at the
            # model's size, so the layer's regions are the rows' regions)
            top = max(r["reliance_per_pixel"] or 0.0 for r in mine)
            levels: dict[int, float] = {}
            for r in mine:
                level = round(255 * LAYER_ALPHA * (r["reliance_per_pixel"] or 0.0) / top) if top > 0 else 0
                levels[level] = levels.get(level, 0.0) + r["area_fraction"]
            assert set(np.unique(alpha).tolist()) <= set(levels)
            for level, area in levels.items():
                assert abs(float(np.mean(alpha == level)) - area) < 1e-5, (cam, step, level)
    assert any(_rgba(b)[..., 3].max() == TOP for cam, _, _ in CAMERAS
               for b in _blobs(live, f"/camera/{cam}/reliance")[1])  # some camera relied on something

    # view's rebuild from the run's files (its recording made unusable, so it is not opened as recorded)
    copy = tmp_path / "copy"
    shutil.copytree(episode.parents[1], copy)
    (copy / "Lift" / "episode_0" / RRD_NAME).write_bytes(b"not a recording" * 10)
    result = build_recording(copy, save=tmp_path / "view.rrd", model=model)
    assert result.source == "files" and result.identical is True, result.frames
    rebuilt = tmp_path / "view.rrd"
    assert _entities(rebuilt) == _entities(live)
    for entity in sorted(layers):
        assert _blobs(rebuilt, entity) == _blobs(live, entity), entity
    scalars = sorted(e for e in _entities(live) if e.startswith("/reliance/"))
    assert scalars and {(r["camera"], r["region"]) for r in rows if r["reliance_share"] is not None} == {
        tuple(e.split("/")[2:]) for e in scalars}
    for entity in scalars:
        assert _scalars(rebuilt, entity) == _scalars(live, entity), entity
    # without the re-simulation there are no masks to draw the map on: the reliance scalars only
    build_recording(copy, save=tmp_path / "maps.rrd", simulate=False)
    entities = _entities(tmp_path / "maps.rrd")
    assert set(scalars) <= entities and not layers & entities

"""Each output sink alone, fed hand-made step records (tiny layout): its files and what it reports for episode.json;
the table the writer loops over; a sink that raises fails the episode as a writer error always did."""

import dataclasses
import json
import threading

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from harness import probes
from harness.outputs import sinks
from harness.outputs.data_files import ActionArrays, AttentionArrays, InputArrays, MetricLines
from harness.outputs.panels import PngPanels
from harness.outputs.rerun_sink import RRD_NAME, RerunRecording
from harness.outputs.rollout_video import RolloutVideo
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink, StepFinisher
from harness.outputs.writers import EpisodeWriter, OutputOptions, WriterError
from harness.probes.attribution.sink import AttributionFiles
from harness.probes.controls.sink import ControlArrays
from tests.outputs.test_writers import HEADS, KEYS, LAYERS, meta, records, tiny_tokens

pytestmark = [  # imageio's ffmpeg reader leaves its pipes to the garbage collector
    pytest.mark.filterwarnings("ignore::ResourceWarning"),
    pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning"),
]

STEPS = 3


def with_extras(recs, **fields_by_step):
    """The records with some fields replaced at some steps: name={step: value}; a probe's name (harness.probes) sets
    its payload in the record's `probes` mapping."""
    names = {cls.name for cls in probes.probes()}
    return [dataclasses.replace(r, **{name: by[r.step] for name, by in fields_by_step.items()
                                      if r.step in by and name not in names},
                                probes={**r.probes, **{name: by[r.step] for name, by in fields_by_step.items()
                                                       if r.step in by and name in names}})
            for r in recs]


def drive(cls, directory, recs, options=None, blocked=(0.01, 0.02, 0.03)):
    """Make one sink alone, give it every record (finished once), end and close it; (sink, its files entries)."""
    options = options or OutputOptions()
    tokens = tiny_tokens()
    finisher = StepFinisher(tokens, options)
    sink = cls(directory, meta(), options, None)
    timings = []
    for r in recs:
        sink.add(finisher(r))
        timings.append({**r.timings, "write": 0.5})
    sink.end()
    end = EpisodeEnd(tokens, {"success": True, "steps": len(recs), "return": 1.0}, tuple(timings), tuple(blocked))
    return sink, sink.close(end)


def files_in(directory):
    return sorted(p.name for p in directory.iterdir())


def test_a_finished_step_is_built_once_with_the_maps_every_sink_reads():
    options = OutputOptions(png_every=0, video=False, bbox=True)  # boxes are drawn only when asked (--bbox)
    step = StepFinisher(tiny_tokens(), options)(records(1)[0])
    assert isinstance(step, FinishedStep) and step.step == 0
    assert step.attention.shape == (LAYERS, HEADS, 1, KEYS) and step.attention.dtype == np.float32
    assert step.maps["image_primary"].shape == (LAYERS, HEADS, 4, 4) and step.maps["image_wrist"].shape == (LAYERS, HEADS, 2, 2)
    assert step.boxes["image_primary"] == (16, 32, 32, 48)  # the 128 px mask's box on the 64 px frame
    assert step.metrics["share/primary"].shape == (LAYERS,) and step.rollout is None
    with pytest.raises(dataclasses.FrozenInstanceError):  # sinks share one record
        step.attention = None


def test_attention_arrays_alone(tmp_path):
    options = OutputOptions(video_attention="rollout")  # the rollout rows are kept too
    recs = with_extras(records(STEPS, full=True), phase={0: "approach", 1: "lift"})
    _, files = drive(AttentionArrays, tmp_path, recs, options)
    assert files == {"attention": "attention.npz"} and files_in(tmp_path) == ["attention.npz"]
    with np.load(tmp_path / "attention.npz") as z:
        assert z["readout_attention"].shape == (STEPS, LAYERS, HEADS, 1, KEYS) and z["readout_attention"].dtype == np.float16
        np.testing.assert_array_equal(z["step"], np.arange(STEPS))
        assert z["metrics/share/primary"].shape == (STEPS, LAYERS) and z["metrics/share/primary"].dtype == np.float32
        assert z["mask_fraction/image_primary/target"].shape == (STEPS, 4, 4)
        assert z["measures/layer/entropy"].shape == (STEPS, LAYERS)
        assert z["measures/head/entropy"].shape == (STEPS, LAYERS, HEADS)
        assert z["rollout_readout"].shape == (STEPS, 1, KEYS) and z["rollout_readout"].dtype == np.float16
        np.testing.assert_array_equal(z["phase"], [0, 2, -1])  # index into phase_names; -1: none recorded
        assert list(z["phase_names"]) == ["approach", "grasp", "lift"] and "tokens/group" in z.files


def test_action_and_input_arrays_alone(tmp_path):
    inputs = {t: {"image_primary": np.full((64, 64, 3), t, np.uint8), "proprio": np.arange(3, dtype=np.float32) + t}
              for t in range(STEPS)}
    recs = with_extras(records(STEPS), policy_inputs=inputs, inferred={1: False})
    _, files = drive(ActionArrays, tmp_path / "a", recs)
    assert files == {"actions": "actions.npz"} and files_in(tmp_path / "a") == ["actions.npz"]
    with np.load(tmp_path / "a" / "actions.npz") as z:
        assert z["predicted"].shape == (STEPS, 4, 7) and z["executed"].shape == (STEPS, 7)
        np.testing.assert_array_equal(z["inferred"], [True, False, True])
        np.testing.assert_array_equal(z["success"], [False, False, True])
        hashes = z["input_hash/image_primary"]
        assert hashes.dtype == np.uint64 and hashes.shape == (STEPS,) and len(set(hashes.tolist())) == STEPS

    assert not InputArrays.wanted(OutputOptions(), None) and InputArrays.wanted(OutputOptions(record_inputs=True), None)
    _, files = drive(InputArrays, tmp_path / "i", recs, OutputOptions(record_inputs=True))
    assert files == {"inputs": "inputs.npz"}
    with np.load(tmp_path / "i" / "inputs.npz") as z:
        assert z["input/image_primary"].shape == (STEPS, 64, 64, 3) and z["input/image_primary"].dtype == np.uint8
        assert z["input/proprio"].shape == (STEPS, 3) and int(z["seed"]) == 7
        assert str(z["instruction"]) == "pick up the red cube"
    with pytest.raises(ValueError, match="record_inputs needs the policy's inputs"):
        drive(InputArrays, tmp_path / "none", records(1), OutputOptions(record_inputs=True))


def test_metric_lines_alone(tmp_path):
    recs = with_extras(records(STEPS), phase={0: "approach", 1: "grasp", 2: "grasp"})
    _, files = drive(MetricLines, tmp_path, recs, blocked=(0.25, 0.5))  # the last step's wait is unknown
    assert files == {"metrics": "metrics.jsonl"} and files_in(tmp_path) == ["metrics.jsonl"]
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 1, 2] and len({tuple(r) for r in rows}) == 1  # the same keys in every row
    assert rows[0]["run"] == "test" and rows[2]["success"] is True and len(rows[0]["share"]["primary"]) == LAYERS
    assert [r["timings"]["blocked"] for r in rows] == [0.25, 0.5, None]
    assert [r["phase"] for r in rows] == ["approach", "grasp", "grasp"]
    assert rows[1]["timings"] == {"simulation": 0.01, "inference": 0.02, "write": 0.5, "blocked": 0.5}


def test_attribution_and_control_files_alone(tmp_path):
    maps = {"saliency": {"image_primary": np.arange(16, dtype=np.float32).reshape(4, 4)}}
    probe = {"maps": maps, "seconds": 0.1, "faithfulness": [{"method": "saliency", "camera": "image_primary"}]}
    control = {"blank": np.full((LAYERS, HEADS, 1, KEYS), 1 / KEYS, np.float32)}
    recs = with_extras(records(STEPS), attribution={1: probe}, controls={0: control, 2: control})

    _, files = drive(AttributionFiles, tmp_path / "a", recs)
    assert files == {"attribution": "attribution.npz", "faithfulness": "faithfulness.jsonl"}
    with np.load(tmp_path / "a" / "attribution.npz") as z:
        np.testing.assert_array_equal(z["step"], [1])
        np.testing.assert_array_equal(z["map/saliency/image_primary"], maps["saliency"]["image_primary"][None])
    (line,) = (tmp_path / "a" / "faithfulness.jsonl").read_text().splitlines()
    assert json.loads(line) == {"run": "test", "task": "Lift", "episode": 0, "seed": 7, "step": 1,
                                "method": "saliency", "camera": "image_primary"}

    _, files = drive(ControlArrays, tmp_path / "c", recs)
    assert files == {"controls": "controls.npz"}
    with np.load(tmp_path / "c" / "controls.npz") as z:
        np.testing.assert_array_equal(z["step"], [0, 2])
        assert z["blank"].shape == (2, LAYERS, HEADS, 1, KEYS) and z["blank"].dtype == np.float16

    for cls in (AttributionFiles, ControlArrays):  # no step carries one: no file
        (tmp_path / cls.__name__).mkdir()
        assert drive(cls, tmp_path / cls.__name__, records(STEPS))[1] == {}
        assert files_in(tmp_path / cls.__name__) == []
    bad = with_extras(records(1), controls={0: {"blank": np.zeros((1, HEADS, 1, KEYS), np.float32)}})
    with pytest.raises(ValueError, match="control 'blank' attention has shape"):
        drive(ControlArrays, tmp_path / "bad", bad)


@pytest.mark.parametrize("workers", [0, 2])
def test_png_panels_alone(tmp_path, workers):
    options = OutputOptions(png_every=2, layers=(0, -1), png_workers=workers, video=False)
    maps = {"saliency": {"image_primary": np.ones((4, 4), np.float32)}}
    recs = with_extras(records(STEPS), attribution={2: {"maps": maps}})
    sink, files = drive(PngPanels, tmp_path, recs, options)
    expected = ["step_0000_layer_00.png", "step_0000_layer_01.png", "step_0002_attribution.png",
                "step_0002_layer_00.png", "step_0002_layer_01.png"]
    assert files_in(tmp_path) == expected
    assert files == {"png_count": 5, "png_pattern": "step_{step:04d}_layer_{layer:02d}.png",
                     "attribution_png_pattern": "step_{step:04d}_attribution.png"}
    assert sink.timings()["png_encode"]["count"] == 5
    for name in expected:
        with Image.open(tmp_path / name) as im:
            assert im.mode == "RGB" and im.width > 128


def test_rollout_video_alone_writes_an_mp4_that_decodes_and_a_gif(tmp_path):
    options = OutputOptions(png_every=0, gif=True, gif_every=2, fps=5)
    assert RolloutVideo.wanted(options, None) and not RolloutVideo.wanted(OutputOptions(video=False), None)
    _, files = drive(RolloutVideo, tmp_path, records(STEPS), options)
    assert files == {"video": "rollout.mp4", "gif": "rollout.gif"}
    assert files_in(tmp_path) == ["rollout.gif", "rollout.mp4"]
    frames = list(iio.imiter(tmp_path / "rollout.mp4"))
    assert len(frames) == STEPS and frames[0].ndim == 3 and frames[0].shape[0] % 16 == 0
    assert frames[0].std() > 10  # a picture, not a blank frame
    assert iio.imread(tmp_path / "rollout.gif").shape[0] == 2  # steps 0 and 2


def test_rerun_recording_alone(tmp_path):
    assert not RerunRecording.wanted(OutputOptions(), None)
    assert RerunRecording.wanted(OutputOptions(rerun=True), None) and RerunRecording.wanted(OutputOptions(), "rerun+http://x")
    (tmp_path / RRD_NAME).write_bytes(b"stale")
    sink, files = drive(RerunRecording, tmp_path, records(STEPS), OutputOptions(rerun=True))
    assert files == {"rerun": RRD_NAME} and files_in(tmp_path) == [RRD_NAME]
    data = (tmp_path / RRD_NAME).read_bytes()
    assert data != b"stale" and len(data) > 1000 and sink.timings()["rerun"] > 0


def test_the_table_holds_one_sink_per_output_and_the_writer_opens_those_asked_for(tmp_path):
    table = sinks.sink_table()
    assert all(issubclass(cls, Sink) for cls in table) and len(set(table)) == len(table)
    names = [type(s).__name__ for s in sinks.open_sinks(tmp_path, meta(), OutputOptions())]
    assert names == ["AttentionArrays", "ActionArrays", "MetricLines", "AttributionFiles", "ControlArrays",
                     "RelianceLines", "ReadoutArrays", "ConsistencyArrays", "PngPanels", "RolloutVideo"]
    chosen = sinks.open_sinks(tmp_path, meta(), OutputOptions(video=False, record_inputs=True, rerun=True))
    assert {"InputArrays", "RerunRecording"} <= {type(s).__name__ for s in chosen}
    assert "RolloutVideo" not in {type(s).__name__ for s in chosen}
    for sink in chosen:
        sink.abort()


class Failing(Sink):
    """A sink that raises at step 1 (as a failing device or a bug in an output would; a full disk stops the run:
    tests/run/test_disk_space.py)."""

    made: list = []

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.aborted = threading.Event()
        Failing.made.append(self)

    def add(self, step):
        if step.step == 1:
            raise OSError(5, "Input/output error")

    def abort(self):
        self.aborted.set()


def test_a_sink_that_raises_fails_the_episode_as_a_writer_error(tmp_path, monkeypatch):
    """As any background-writer error: the next add_step or finish raises WriterError naming the step and the
    cause; abort removes temporaries, aborts every sink and writes no episode.json."""
    table = sinks.sink_table()
    monkeypatch.setattr(sinks, "sink_table", lambda: (*table, Failing))
    writer = EpisodeWriter(tmp_path, tiny_tokens(), meta(), OutputOptions(png_every=0))
    recs = records(STEPS)
    writer.add_step(recs[0])
    writer.add_step(recs[1])
    with pytest.raises(WriterError, match=r"background writer failed at step 1: OSError\(5, 'Input/output error") as info:
        for r in recs[2:]:
            writer.add_step(r)
        writer.finish({"success": True})
    assert isinstance(info.value.__cause__, OSError)
    writer.abort()
    assert Failing.made[-1].aborted.is_set()
    assert not list(tmp_path.glob("*.tmp*")) and not (tmp_path / "episode.json").exists()
    assert not (tmp_path / "rollout.mp4").exists() and not (tmp_path / "attention.npz").exists()


@pytest.mark.slow
def test_a_sink_that_raises_is_a_failed_episode_row(fixtures_dir, tmp_path, monkeypatch):
    """Through a real run (tiny model, Lift, 3 steps): the episode's row is `failed` with the WriterError line and
    its episode.json records it, as for any writer error; nothing half-written stays."""
    from harness.octo import load_pretrained
    from harness.run import Protocol, execute

    table = sinks.sink_table()
    monkeypatch.setattr(sinks, "sink_table", lambda: (*table, Failing))
    model = load_pretrained(str(fixtures_dir / "tiny"))
    protocol = Protocol(model=model.source, tasks=("Lift",), max_steps=STEPS,
                        outputs=OutputOptions(png_every=0, video=False))
    summary = execute(protocol, tmp_path, "r", model=model, progress=False)
    (row,) = summary.rows
    assert row.status == "failed"
    assert row.error.startswith("WriterError: background writer failed at step 1: OSError(5, 'Input/output error")
    episode = summary.episode_dir(row)
    info = json.loads((episode / "episode.json").read_text())
    assert info["status"] == "failed" and info["error"] == row.error
    assert not list(episode.glob("*.tmp*")) and not (episode / "attention.npz").exists()

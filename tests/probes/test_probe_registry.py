"""The probe registry (harness.probes), tested by its design's promise: a per-step probe defined here, in tests/, and
registered at run time appears in the run folder, the report and the viewer, with no file under harness/ or envs/
changed for it; and the registry keeps the built-in probes' order, parts and stages."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from harness import probes
from harness.files import json_safe, write_atomic
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink

NAME = "action_norm"
EVERY = 2  # every second step the policy infers at (temporal ensembling infers at every step: steps 0, 2, 4)
FILE = "action_norm.jsonl"


class NormLines(Sink):
    """action_norm.jsonl: one row per probed step, {"step", "norm"}."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.rows: list[dict] = []

    def add(self, step: FinishedStep) -> None:
        payload = step.record.probes.get(NAME)
        if payload is not None:
            self.rows.append({"step": step.step, **payload})

    def close(self, end: EpisodeEnd) -> dict:
        if not self.rows:
            return {}
        text = "".join(json.dumps(json_safe(row)) + "\n" for row in self.rows)
        write_atomic(self.dir / FILE, lambda f: f.write(text.encode()))
        return {NAME: FILE}


class NormReader:
    @staticmethod
    def by_step(directory) -> dict[int, dict]:
        path = Path(directory) / FILE
        rows = [json.loads(line) for line in path.read_text().splitlines()] if path.is_file() else []
        return {row["step"]: {"norm": row["norm"]} for row in rows}


class NormSection:
    """A report section: per run and task, the mean norm over the probed steps (tables/action_norm.csv)."""

    name, anchor = "Action norm", NAME

    def summarise(self, runs, options):
        reader = probes.part(NAME, "reader")  # reached through the registry, as the report's own sections do
        rows = []
        for run in runs:
            for episode in run.record.episodes:
                norms = [p["norm"] for p in reader.by_step(episode.directory).values()]
                if norms:
                    rows.append((run.record.name, episode.task, episode.episode, len(norms), float(np.mean(norms))))
        return rows

    def tables(self, runs, summary):
        if not summary:
            return {}
        lines = ["run,task,episode,steps,mean_norm"] + [",".join(str(v) for v in row) for row in summary]
        return {"action_norm.csv": ("\n".join(lines) + "\n").encode()}

    def section(self, runs, figures, summary):
        if not summary:
            return ""
        from harness.report import html as H

        rows = [(r[1], r[2], r[3], f"{r[4]:.4f}") for r in summary]
        return H.section(self.name, H.table(["task", "episode", "steps", "mean norm"], rows), anchor=NAME)


class NormLayer:
    @staticmethod
    def camera_views(cam, payload):
        return []

    @staticmethod
    def camera_note(payload):
        return ""

    @staticmethod
    def plots(payload):
        import rerun.blueprint as rrb

        return [rrb.TimeSeriesView(origin=NAME, name="the first action's norm")]

    @staticmethod
    def header(payload):
        return ["- action_norm: the norm of the chunk's first action, every second inferred step"]

    @staticmethod
    def log(recording, record, payload):
        recording.scalars(f"{NAME}/first_action", float(payload["norm"]), ["action norm"])


class ActionNorm(probes.Probe):
    """The norm of the predicted chunk's first action, every EVERY-th inferred step (on while registered)."""

    name = NAME
    sink, reader, section, layer = NormLines, NormReader, NormSection(), NormLayer()

    @classmethod
    def every(cls, config) -> int:
        return EVERY

    def run(self, batch, context):
        return [{"norm": float(np.linalg.norm(item.chunk[0]))} for item in batch]


def test_the_built_in_probes_keep_their_order_parts_and_files():
    """attribution, controls, reliance, readout_features, action_consistency in that order (the order they run in at a
    step and their files are written in); each names its sink, and the parts resolve; a name taken twice is refused;
    off unless its option is set."""
    from harness.outputs import sinks
    from harness.policy import PolicyConfig

    assert [cls.name for cls in probes.probes()] == ["attribution", "controls", "reliance", "readout_features",
                                                     "action_consistency"]
    table = [cls.__name__ for cls in sinks.sink_table()]
    assert table[4:9] == ["AttributionFiles", "ControlArrays", "RelianceLines", "ReadoutArrays", "ConsistencyArrays"]
    assert [cls.name for cls, _ in probes.parts("layer")] == ["attribution", "reliance"]
    assert [cls.name for cls, _ in probes.parts("section")] == ["attribution", "reliance"]
    assert probes.active(PolicyConfig()) == ()
    on = PolicyConfig(attribution="saliency", attention_controls="blank", controls_every=3, reliance_every=4,
                      readout_features_every=5, action_consistency=True)
    assert [(cls.name, cls.every(on)) for cls in probes.active(on)] == [("attribution", 1), ("controls", 3),
                                                                         ("reliance", 4), ("readout_features", 5),
                                                                         ("action_consistency", 1)]
    clash = type("Clash", (probes.Probe,), {"name": "reliance"})
    with pytest.raises(ValueError, match="taken"):
        probes.register(clash)
    with pytest.raises(KeyError, match="no probe named"):
        probes.get("nothing")


def test_each_built_in_probe_reads_back_what_its_sink_wrote(tmp_path):
    """Each probe's sink alone on hand-made records, then its reader (found through the registry): the payloads by
    step, as view's rebuild of a recording hands them to the viewer layers (controls as float16, as stored)."""
    from tests.outputs.test_sinks import STEPS, drive, with_extras
    from tests.outputs.test_writers import HEADS, KEYS, LAYERS, records

    maps = {"saliency": {"image_primary": np.arange(16, dtype=np.float32).reshape(4, 4)}}
    control = {"blank": np.random.default_rng(0).random((LAYERS, HEADS, 1, KEYS)).astype(np.float32)}
    rows = [{"step": 0, "camera": "image_primary", "region": "target", "fill": "mean", "change": 0.5,
             "area_fraction": 0.25, "reliance_per_pixel": 2.0, "reliance_share": 1.0, "camera_change": 0.5}]
    payloads = {"attribution": {1: {"maps": maps}}, "controls": {0: control, 2: control},
                "reliance": {0: {"rows": rows}}, "readout_features": {1: {"features": np.ones(8, np.float32)}},
                "action_consistency": {0: {}, 2: {}}}
    recs = with_extras(records(STEPS), **payloads)
    assert [cls.name for cls, _ in probes.parts("reader")] == ["attribution", "controls", "reliance",
                                                                "readout_features", "action_consistency"]
    for cls, reader in probes.parts("reader"):
        drive(probes.part(cls, "sink"), tmp_path / cls.name, recs)
        read = reader.by_step(tmp_path / cls.name)
        assert sorted(read) == sorted(payloads[cls.name]), cls.name
        assert reader.by_step(tmp_path / "nothing") == {}
    read = probes.part("controls", "reader").by_step(tmp_path / "controls")
    np.testing.assert_array_equal(read[2]["blank"], control["blank"].astype(np.float16).astype(np.float32))
    attribution = probes.part("attribution", "reader").by_step(tmp_path / "attribution")
    np.testing.assert_array_equal(attribution[1]["maps"]["saliency"]["image_primary"], maps["saliency"]["image_primary"])
    assert probes.part("reliance", "reader").by_step(tmp_path / "reliance")[0]["rows"][0]["reliance_share"] == 1.0


def test_no_module_outside_the_probes_imports_a_particular_probe():
    """Consumers (policy, sinks, report, viewer, robustness, compare) reach probes through the registry
    (`harness.probes` or `harness.probes.registry`), never a particular probe's module."""
    from tests.test_layout import HARNESS, import_graph

    graph = import_graph()
    assert "harness.probes.reliance.reader" in graph
    reaching = sorted(f"{a} imports {b}" for a in graph if not a.startswith("harness.probes")
                      for b in graph[a] if b.startswith("harness.probes.") and b != "harness.probes.registry")
    assert reaching == []
    outside = sorted(str(p.relative_to(HARNESS.parent)) for root in (HARNESS, HARNESS.parent / "envs")
                     for p in root.rglob("*.py") if "reliance" in p.read_text()
                     and "probes" not in p.relative_to(HARNESS.parent).parts)
    # 8: diagnose reads nuisance reliance as one of its failure signals (analysis/diagnose/signals.py, failures.py:
    # issue 74 names it), through the registry's reader
    assert len(outside) <= 8, outside


@pytest.mark.slow
def test_a_probe_defined_here_appears_in_the_run_folder_the_report_and_the_viewer(fixtures_dir, tmp_path):
    """A real run of the tiny fixture (Lift, 5 steps, --rerun save) through the command line with ActionNorm
    registered: its file holds the norms of the predicted chunks at steps 0, 2, 4 and is digested in the run's row;
    the report has its section and table; the recording has its series and its header line. Unregistered, it is gone."""
    import rerun as rr

    from harness import cli

    assert ActionNorm.__module__ == __name__  # defined here, nothing under harness/ names it
    run = tmp_path / "r"
    with probes.registered(ActionNorm):
        assert cli.main(["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--out", str(tmp_path),
                         "--run-name", "r", "--max-steps", "5", "--png-every", "0", "--no-video", "--fast-render",
                         "--rerun", "save"]) == 0
        assert cli.main(["report", str(run), "--out", str(tmp_path / "report")]) == 0
    assert NAME not in [cls.name for cls in probes.probes()]

    episode = run / "Lift" / "episode_0"
    rows = [json.loads(line) for line in (episode / FILE).read_text().splitlines()]
    predicted = np.load(episode / "actions.npz")["predicted"]  # (steps, horizon, action_dim)
    assert [r["step"] for r in rows] == [0, 2, 4]
    assert np.allclose([r["norm"] for r in rows], [np.linalg.norm(predicted[s][0]) for s in (0, 2, 4)], rtol=1e-5)
    assert json.loads((episode / "episode.json").read_text())["files"][NAME] == FILE
    (row,) = [json.loads(line) for line in (run / "results.jsonl").read_text().splitlines()]
    assert FILE in row["files"]  # digested like the built-in probes' files

    page = (tmp_path / "report" / "report.html").read_text()
    assert "<h2>Action norm</h2>" in page and f"<a href='#{NAME}'>Action norm</a>" in page
    table = (tmp_path / "report" / "tables" / "action_norm.csv").read_text().splitlines()
    assert table[0] == "run,task,episode,steps,mean_norm" and table[1].startswith("r,Lift,0,3,")

    recording = rr.dataframe.load_recording(str(episode / "episode.rrd"))
    entity = f"/{NAME}/first_action"
    read = recording.view(index="step", contents=entity).select(columns=["step", f"{entity}:Scalar"]).read_all()
    logged = [(s, v[0]) for s, v in zip(read.column("step").to_pylist(), read.column(f"{entity}:Scalar").to_pylist())
              if v is not None]
    assert [s for s, _ in logged] == [0, 2, 4] and np.allclose([v for _, v in logged], [r["norm"] for r in rows])
    header = recording.view(index="step", contents="/episode/instruction").select_static().read_all()
    assert "action_norm: the norm of the chunk's first action" in str(header.to_pydict())

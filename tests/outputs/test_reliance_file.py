"""reliance.jsonl (--reliance-every): the RelianceLines sink alone on hand-made step records, its place in the sink
table, the run-level refusal without masks, and a real short run whose episode writes and digests the file."""

from __future__ import annotations

import json

import pytest

from harness.outputs import sinks
from harness.probes.reliance.sink import RelianceLines
from tests.outputs.test_sinks import STEPS, drive, files_in, with_extras
from tests.outputs.test_writers import records


def _rows(step):
    return [{"step": step, "camera": "image_primary", "region": region, "fill": "impute", "change": change,
             "area_fraction": 0.25, "reliance_per_pixel": change / 0.25, "reliance_share": share, "camera_change": 0.4}
            for region, change, share in (("target", 0.3, 0.75), ("background", 0.1, 0.25))]


def test_reliance_lines_alone_write_one_row_per_step_camera_and_region_with_the_episode_ids(tmp_path):
    recs = with_extras(records(STEPS), reliance={0: {"rows": _rows(0), "seconds": 0.5},
                                                 2: {"rows": _rows(2), "seconds": 0.25}})
    sink, files = drive(RelianceLines, tmp_path, recs)
    assert files == {"reliance": "reliance.jsonl"} and files_in(tmp_path) == ["reliance.jsonl"]
    rows = [json.loads(line) for line in (tmp_path / "reliance.jsonl").read_text().splitlines()]
    assert [(r["step"], r["region"]) for r in rows] == [(0, "target"), (0, "background"), (2, "target"), (2, "background")]
    assert {k: rows[0][k] for k in ("run", "task", "episode", "seed")} == {
        k: getattr(sink.meta, k) for k in ("run", "task", "episode", "seed")}
    assert rows[0]["reliance_share"] == 0.75 and sink.timings() == {"reliance": 0.75}


def test_no_reliance_step_writes_no_file_and_the_sink_is_in_the_table(tmp_path):
    _, files = drive(RelianceLines, tmp_path, records(STEPS))
    assert files == {} and files_in(tmp_path) == []
    assert RelianceLines in sinks.sink_table()


def test_reliance_without_masks_is_one_line_before_anything_loads(fixtures_dir, tmp_path, capsys):
    from harness import cli

    code = cli.main(["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--out", str(tmp_path),
                     "--reliance-every", "2", "--no-masks"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--reliance-every" in err[0] and "--no-masks" in err[0]
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
def test_a_run_with_reliance_every_writes_and_digests_reliance_jsonl(fixtures_dir, tmp_path):
    from harness import cli

    assert cli.main(["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--out", str(tmp_path),
                     "--run-name", "r", "--max-steps", "3", "--reliance-every", "2", "--reliance-fill", "mean",
                     "--png-every", "0", "--no-video", "--fast-render"]) == 0
    episode = tmp_path / "r" / "Lift" / "episode_0"
    rows = [json.loads(line) for line in (episode / "reliance.jsonl").read_text().splitlines()]
    assert sorted({r["step"] for r in rows}) == [0, 2]  # steps 0 and 2 of 3
    assert {r["camera"] for r in rows} == {"image_primary", "image_wrist"} and {r["fill"] for r in rows} == {"mean"}
    assert "target" in {r["region"] for r in rows} and "gripper" in {r["region"] for r in rows}
    result = [json.loads(line) for line in (tmp_path / "r" / "results.jsonl").read_text().splitlines()][0]
    assert "reliance.jsonl" in result["files"]  # digested like the other data files
    manifest = json.loads((tmp_path / "r" / "manifest.json").read_text())
    assert manifest["protocol"]["policy"]["reliance_every"] == 2 and manifest["protocol"]["policy"]["reliance_fill"] == "mean"

"""What a run writes is decided once (issue 43 item 6): `--ci-method` is recorded in the manifest (outside the protocol
and its hash) and a resume, `--resume RUN_DIR` included, writes the derived files with it, so a resumed run's derived
files equal an uninterrupted run's, byte for byte but for timings; the same command without the flag resumes it with
the recorded method, and another method is refused (issue 42's "--ci-method survives resume", merged here)."""

from __future__ import annotations

import csv
import json
import shutil

import pytest

from harness import cli

TIMINGS = ("seconds_per_step", "simulation_per_step", "inference_per_step", "overhead_fraction")


def _without_timings(rows: list[dict]) -> list[dict]:
    """Rows without their timings; of the digests, the arrays' (metrics.jsonl holds each step's timings and the run
    name)."""
    return [{**{k: v for k, v in row.items() if k not in TIMINGS},
             "files": {name: d for name, d in row["files"].items() if name.endswith(".npz")}} for row in rows]


@pytest.mark.slow
def test_a_resumed_clopper_pearson_run_keeps_its_intervals_and_its_derived_files(fixtures_dir, tmp_path, capsys):
    from harness.runfolder.schema import protocol_hash

    # made on the command line (the flag reaches the driver)
    command = ["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--max-steps", "2", "--png-every", "0",
               "--no-video", "--no-masks", "--fast-render", "--out", str(tmp_path), "--run-name", "full"]
    assert cli.main([*command, "--ci-method", "clopper-pearson"]) == 0
    full = tmp_path / "full"
    manifest = json.loads((full / "manifest.json").read_text())
    assert manifest["statistics"] == {"ci_method": "clopper-pearson", "confidence": 0.95}
    assert manifest["protocol_hash"] == protocol_hash(manifest["protocol"])  # the protocol (and its hash) unchanged

    # interrupted before its episode was recorded: the same run folder without the row and the episode's files
    resumed = tmp_path / "resumed"
    shutil.copytree(full, resumed)
    (resumed / "results.jsonl").write_text("")
    shutil.rmtree(resumed / "Lift" / "episode_0")
    assert cli.main(["run", "--resume", str(resumed)]) == 0
    assert "clopper-pearson" in capsys.readouterr().out

    assert (resumed / "statistics.csv").read_bytes().replace(b"resumed", b"full") == \
        (full / "statistics.csv").read_bytes()
    method = {row["method"] for row in csv.DictReader((resumed / "statistics.csv").open())}
    assert method == {"clopper-pearson"}
    a, b = (json.loads((run / "results.json").read_text()) for run in (full, resumed))
    assert a["statistics"] == b["statistics"] and a["status"] == b["status"] == "complete"
    assert _without_timings(a["episodes"]) == [{**row, "run": "full"} for row in _without_timings(b["episodes"])]

    # a finished run resumed with --resume rewrites its derived files as they were (before: Wilson intervals)
    before = (full / "statistics.csv").read_bytes(), (full / "summary.csv").read_bytes()
    assert cli.main(["run", "--resume", str(full)]) == 0
    assert ((full / "statistics.csv").read_bytes(), (full / "summary.csv").read_bytes()) == before

    # the same command without the flag resumes it with the recorded method; another method is one line, exit 2
    assert cli.main(command) == 0 and (full / "statistics.csv").read_bytes() == before[0]
    capsys.readouterr()
    assert cli.main([*command, "--ci-method", "wilson"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--ci-method clopper-pearson" in err[0]

"""What a run writes is decided once (issue 43 item 6): `--ci-method` is recorded in the manifest (outside the protocol
and its hash) and a resume, `--resume RUN_DIR` included, writes the derived files with it, so a resumed run's derived
files equal an uninterrupted run's, byte for byte but for timings."""

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
    from envs.options import EnvOptions
    from harness.outputs.writers import OutputOptions
    from harness.run.driver import execute
    from harness.run.protocol import Protocol
    from harness.runfolder.schema import protocol_hash

    protocol = Protocol(model=str(fixtures_dir / "tiny"), tasks=("Lift",), episodes=1, max_steps=2,
                        env=EnvOptions(masks=False, fast_render=True), outputs=OutputOptions(png_every=0, video=False))
    full = execute(protocol, tmp_path, "full", progress=False, ci_method="clopper-pearson").run_dir
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

    # another method for a run that records one is refused (one line on the command line, exit 2), before any model
    from harness.run.driver import ProtocolMismatchError

    with pytest.raises(ProtocolMismatchError, match="statistics.ci_method.*--ci-method clopper-pearson"):
        execute(protocol, tmp_path, "full", progress=False, ci_method="wilson")

"""`--ci-method` survives a resume (issue 42): a run made on the command line with `--ci-method clopper-pearson`,
interrupted and resumed with `run --resume RUN_DIR` (or the same command without the flag), keeps its intervals;
another method for it is one line, exit 2. The method is the field RunStatistics.ci_method, recorded in the
manifest's "statistics" (outside the protocol's hash: the episodes are the same)."""

from __future__ import annotations

import csv
import json
import shutil

import pytest

from harness import cli


def _methods(run) -> set[str]:
    return {row["method"] for row in csv.DictReader((run / "statistics.csv").open())}


@pytest.mark.slow
def test_a_clopper_pearson_run_resumed_from_the_command_line_keeps_it(fixtures_dir, tmp_path, capsys):
    command = ["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--max-steps", "2", "--png-every", "0",
               "--no-video", "--no-masks", "--fast-render", "--out", str(tmp_path), "--run-name", "exact"]
    assert cli.main([*command, "--ci-method", "clopper-pearson"]) == 0
    run = tmp_path / "exact"
    assert json.loads((run / "manifest.json").read_text())["statistics"]["ci_method"] == "clopper-pearson"
    assert _methods(run) == {"clopper-pearson"}
    made = (run / "statistics.csv").read_bytes()

    # interrupted before its episode was recorded, then resumed from the manifest alone
    (run / "results.jsonl").write_text("")
    shutil.rmtree(run / "Lift" / "episode_0")
    (run / "statistics.csv").unlink()
    capsys.readouterr()
    assert cli.main(["run", "--resume", str(run)]) == 0
    assert "clopper-pearson" in capsys.readouterr().out
    assert _methods(run) == {"clopper-pearson"} and (run / "statistics.csv").read_bytes() == made

    # the same command without the flag resumes it with the recorded method; another method is refused
    assert cli.main(command) == 0 and (run / "statistics.csv").read_bytes() == made
    capsys.readouterr()
    assert cli.main([*command, "--ci-method", "wilson"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--ci-method clopper-pearson" in err[0]
    assert _methods(run) == {"clopper-pearson"}

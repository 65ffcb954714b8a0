"""A suite defined outside envs/ and harness/ runs end to end (issue 72 item 2): the toy suite of tests/envs/toy_suite.py
(numpy-drawn cameras, a 7-D action, a success signal, masks), registered through the entry-point group
octo_harness.suites of a temporary distribution folder (a .dist-info with entry_points.txt, never installed into the
shared virtual environment), runs through `octo-harness run` with the tiny fixture model, sequentially and with
`--workers 2`. The spawned workers import the harness afresh: they find the suite only through the entry point on the
path they inherit. Both runs' episodes are the same, action for action."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from envs import suites
from tests.envs import toy_suite

ENTRY_POINTS = "[octo_harness.suites]\ntoy = tests.envs.toy_suite:ToySuite\n"
METADATA = "Metadata-Version: 2.1\nName: toy-suite\nVersion: 0.1\n"


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """The toy suite registered in this process, and its distribution on the path the spawned workers inherit (the
    registry of this process is loaded before, so the entry point adds nothing here and nothing stays registered)."""
    folder = tmp_path_factory.mktemp("dist")
    info = folder / "toy_suite-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(METADATA)
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    suites.suites()
    sys.path.insert(0, str(folder))
    try:
        with suites.registered(toy_suite.ToySuite):
            yield folder
    finally:
        sys.path.remove(str(folder))


def _run(fixtures_dir: Path, out: Path, name: str, *extra: str) -> int:
    from harness import cli

    return cli.main(["run", "--task", "toy", "--model", str(fixtures_dir / "tiny"), "--episodes", "1", "--seed", "3",
                     "--max-steps", "3", "--png-every", "0", "--no-video", "--out", str(out), "--run-name", name,
                     *extra])


def _actions(run: Path) -> dict[str, np.ndarray]:
    return {str(p.relative_to(run)): np.load(p)["executed"] for p in sorted(run.rglob("actions.npz"))}


@pytest.mark.slow
def test_a_toy_suite_from_an_entry_point_runs_sequentially_and_with_two_workers(toy, fixtures_dir, tmp_path,
                                                                                monkeypatch):
    assert [t.name for t in suites.get("toy").tasks()] == ["toy/square", "toy/far"]
    assert _run(fixtures_dir, tmp_path, "sequential") == 0
    pids = tmp_path / "pids"
    monkeypatch.setenv(toy_suite.PIDS, str(pids))
    assert _run(fixtures_dir, tmp_path, "workers", "--workers", "2") == 0
    made_in = {int(line) for line in pids.read_text().split()}
    assert made_in - {os.getpid()}  # the workers made envs too (this process only the one the model is checked on)
    manifest = json.loads((tmp_path / "workers" / "manifest.json").read_text())
    assert manifest["protocol"]["tasks"] == ["toy/square", "toy/far"]
    assert manifest["conventions"]["toy"]["image_convention"] == "default:toy"
    sequential, workers = _actions(tmp_path / "sequential"), _actions(tmp_path / "workers")
    assert sorted(sequential) == sorted(workers) == ["toy/far/episode_0/actions.npz",
                                                    "toy/square/episode_0/actions.npz"]
    for key, executed in sequential.items():
        assert executed.shape[1] == 7
        np.testing.assert_array_equal(workers[key], executed)
    for run in ("sequential", "workers"):
        episode = json.loads((tmp_path / run / "toy" / "square" / "episode_0" / "episode.json").read_text())
        assert episode["instruction"] == "move the square to the goal" and episode["steps"] >= 1


def test_the_toy_suite_answers_for_its_names(toy):
    from envs.resolver import resolve_names

    assert resolve_names(["TOY", "Lift"]) == ("toy/square", "toy/far", "Lift")
    assert suites.of("toy/far").name == "toy" and suites.of("libero_object").runs == "server"
    with pytest.raises(ValueError, match="toy tasks: toy/square, toy/far"):
        suites.get_task("toy/near")

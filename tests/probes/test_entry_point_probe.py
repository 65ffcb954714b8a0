"""A probe shipped in a package of its own (issue 72): registered through the entry-point group octo_harness.probes,
with an option of its own, it runs under `--workers 2` and under Ray, with no file of harness/ or envs/ changed.

The package is a temporary distribution folder (a module and its .dist-info with entry_points.txt) put on PYTHONPATH
of the commands this test starts, never installed into the shared virtual environment (where the other test process
would load it too). Each command is the real console entry point in a process of its own; its spawned workers and
Ray's workers import the harness afresh and must find the probe through the entry point."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

MODULE = '''
import json
from dataclasses import dataclass

import numpy as np

from harness.options import option
from harness.probes.registry import Probe


@dataclass(frozen=True)
class ChunkNormOptions:
    chunk_norm_every: int = option(0, "--chunk-norm-every", "the predicted chunk's L1 norm every N-th inferred step",
                                   type=int, file=(int,), metavar="N", sparse=True)

    def check(self):
        if self.chunk_norm_every < 0:
            raise ValueError(f"--chunk-norm-every must be >= 0, got {self.chunk_norm_every}")


class ChunkNorm(Probe):
    name = "chunk_norm"
    option = "chunk_norm_every"
    options = ChunkNormOptions
    sink = "chunk_norm_probe:Lines"

    @classmethod
    def every(cls, config):
        return int(config.chunk_norm_every)

    def run(self, batch, context):
        return [{"norm": float(np.abs(item.chunk).sum()), "pid": __import__("os").getpid()} for item in batch]


def _sink_base():
    from harness.outputs.steps import Sink
    return Sink


class Lines(_sink_base()):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.rows = []

    def add(self, step):
        payload = step.record.probes.get("chunk_norm")
        if payload is not None:
            self.rows.append({"step": step.step, **payload})

    def close(self, end):
        from harness.files import write_atomic
        text = "".join(json.dumps(row) + "\\n" for row in self.rows)
        write_atomic(self.dir / "chunk_norm.jsonl", lambda f: f.write(text.encode()))
        return {"chunk_norm": "chunk_norm.jsonl"}
'''
ENTRY_POINTS = "[octo_harness.probes]\nchunk_norm = chunk_norm_probe:ChunkNorm\n"
METADATA = "Metadata-Version: 2.1\nName: chunk-norm-probe\nVersion: 0.1\n"
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def distribution(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("dist")
    (folder / "chunk_norm_probe.py").write_text(MODULE)
    info = folder / "chunk_norm_probe-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(METADATA)
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    return folder


def _run(distribution: Path, fixtures_dir: Path, out: Path, name: str, episodes: int,
         *extra: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(distribution), os.environ.get("PYTHONPATH", "")]),
           "HF_HUB_OFFLINE": "1"}
    argv = [sys.executable, "-m", "harness.cli", "run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"),
            "--episodes", str(episodes), "--max-steps", "3", "--chunk-norm-every", "2", "--png-every", "0", "--no-video",
            "--fast-render", "--no-masks", "--out", str(out), "--run-name", name, *extra]
    return subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)


def _rows(run: Path, episodes: int) -> dict[int, list[dict]]:
    return {e: [json.loads(line) for line in (run / "Lift" / f"episode_{e}" / "chunk_norm.jsonl").read_text().splitlines()]
            for e in range(episodes)}


# two env workers; under Ray one env actor and the policy replica (where the probe runs: a process Ray started, which
# finds the probe only through the entry point), one episode, to keep Ray's start-up on 2 cores short
@pytest.mark.slow
@pytest.mark.parametrize("executor,episodes", [(("--workers", "2"), 2), (("--executor", "ray", "--workers", "1"), 1)],
                         ids=["workers", "ray"])
def test_an_entry_point_probe_runs_under_workers_and_ray(distribution, fixtures_dir, tmp_path, executor, episodes):
    proc = _run(distribution, fixtures_dir, tmp_path, "run", episodes, *executor)
    assert proc.returncode == 0, proc.stderr[-3000:]
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert manifest["protocol"]["policy"]["chunk_norm_every"] == 2  # its option is part of the protocol
    rows = _rows(tmp_path / "run", episodes)
    assert all([r["step"] for r in rows[e]] == [0, 2] for e in range(episodes)), rows
    assert all(r["norm"] > 0 for e in rows.values() for r in e)
    assert all(r["pid"] != os.getpid() for e in rows.values() for r in e)


def test_without_the_distribution_the_option_is_unknown(fixtures_dir, tmp_path):
    """The same command without the package on the path: argparse refuses the probe's flag (exit 2), so the rows
    above came through the entry point."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, "-m", "harness.cli", "run", "--task", "Lift", "--chunk-norm-every", "2"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "--chunk-norm-every" in proc.stderr

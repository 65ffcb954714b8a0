"""The CI recipe (examples/ci/) works as written: its script makes a baseline once, gates a candidate with
`octo-harness regress` and maps the exit code to pass (0), fail (1) or no verdict (2).

Run on the tiny reference fixture (1 Lift episode of 1 step). That model never succeeds, so a worse candidate
cannot lose successes; the degraded candidate is caught by `FAIL_ON=changed` (its numerics on the baseline's
recorded inputs change). The damaged candidate's checkpoint is cut in half.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "examples" / "ci" / "regress-gate.sh"
WORKFLOW = REPO / "examples" / "ci" / "github-actions.yml"

pytestmark = pytest.mark.slow


def gate(candidate: Path, work: Path) -> subprocess.CompletedProcess:
    """The script as a CI job runs it, from the repository root, with a small protocol and its own folders."""
    harness = Path(sys.executable).with_name("octo-harness")
    env = {**os.environ, "BASELINE": str(work / "baseline"), "BASELINE_MODEL": str(work / "same"),
           "TASKS": "Lift", "EPISODES": "1", "MAX_STEPS": "1", "FAIL_ON": "changed", "OUT": str(work / "runs"),
           "PYTHON": sys.executable, "OCTO_HARNESS": str(harness) if harness.exists() else "octo-harness"}
    return subprocess.run(["bash", str(SCRIPT), str(candidate)], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=600)


def degraded_copy(source: Path, dest: Path) -> Path:
    """The checkpoint with the action head's kernels scaled by 1.5: same architecture, other actions."""
    import flax.serialization as serialization

    shutil.copytree(source, dest)
    path = next(dest.glob("*/default/checkpoint"))
    tree = serialization.msgpack_restore(path.read_bytes())
    head = tree["heads_action"]

    def scale(node):
        for key, value in node.items():
            if isinstance(value, dict):
                scale(value)
            elif key == "kernel":
                node[key] = (np.asarray(value) * 1.5).astype(value.dtype)

    scale(head)
    path.write_bytes(serialization.msgpack_serialize(tree))
    return dest


@pytest.fixture(scope="module")
def work(fixtures_dir, tmp_path_factory):
    """A folder holding the candidates and, after the first gate (an identical candidate), the baseline."""
    work = tmp_path_factory.mktemp("ci")
    shutil.copytree(fixtures_dir / "tiny", work / "same")
    first = gate(work / "same", work)
    return work, first


def test_an_identical_candidate_makes_the_baseline_once_and_passes(work):
    folder, first = work
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    assert "making it once" in first.stdout and "gate: PASS" in first.stdout
    assert "IDENTICAL" in first.stdout
    assert (folder / "baseline" / "BASELINE.json").is_file()


def test_a_degraded_candidate_fails(work):
    folder, _ = work
    done = gate(degraded_copy(folder / "same", folder / "degraded"), folder)
    assert done.returncode == 1, done.stdout[-2000:] + done.stderr[-2000:]
    assert "making it once" not in done.stdout  # the baseline is made once
    assert "CHANGED" in done.stdout and "gate: FAIL" in done.stdout


def test_a_damaged_candidate_gives_no_verdict(work):
    folder, _ = work
    damaged = folder / "damaged"
    shutil.copytree(folder / "same", damaged)
    checkpoint = next(damaged.glob("*/default/checkpoint"))
    checkpoint.write_bytes(checkpoint.read_bytes()[: checkpoint.stat().st_size // 2])
    done = gate(damaged, folder)
    assert done.returncode == 2, done.stdout[-2000:] + done.stderr[-2000:]
    assert "gate: ERROR: invalid input" in done.stderr
    assert "Traceback" not in done.stderr


def test_the_workflow_runs_the_script_and_caches_the_baseline():
    workflow = yaml.safe_load(WORKFLOW.read_text())
    steps = workflow["jobs"]["gate"]["steps"]
    runs = [s.get("run", "") for s in steps]
    assert any(r.strip().startswith("bash examples/ci/regress-gate.sh") for r in runs)
    cache = next(s for s in steps if s.get("uses", "").startswith("actions/cache"))
    assert cache["with"]["path"] == "${{ env.BASELINE }}"
    assert workflow["env"]["BASELINE"] and workflow["env"]["CANDIDATE"] and workflow["env"]["BASELINE_MODEL"]
    for path in (workflow["env"]["CANDIDATE"], workflow["env"]["BASELINE_MODEL"]):
        assert (REPO / path / "config.json").is_file(), path  # the example's models exist in this repository

"""The CI recipe (examples/ci/) gates a pull request against its base, never against the candidate itself
(issue 71 item 4): its script makes a baseline once, from the checkpoint as it is at the base commit
(OCTO_GATE_BASE_REV), gates a candidate with `octo-harness regress` and maps the exit code to pass (0), fail (1) or
no verdict (2).

The pull-request case is played in a temporary git repository: the tiny reference fixture is committed as the base at
models/policy, and the pull request replaces it in place, at the same path. The tiny model never succeeds (1 Lift
episode of 1 step here), so a worse candidate cannot lose successes; a degraded candidate (its action head's kernels
scaled by 1.5) is caught by OCTO_GATE_FAIL_ON=changed: its numerics on the baseline's recorded inputs change. A
damaged candidate's checkpoint is cut in half.

Every gate runs with the generic names the script once read (OUT set to a file, TASKS, EPISODES, BASELINE, ...) set
in its environment to values that would break it: they must have no effect.
"""

from __future__ import annotations

import os
import re
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
MODEL = "models/policy"  # the checkpoint's path in the temporary repository, at the base and in the pull request

pytestmark = pytest.mark.slow


def git(repo: Path, *args: str) -> str:
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@t", "GIT_CONFIG_GLOBAL": os.devnull, "GIT_CONFIG_NOSYSTEM": "1"}
    return subprocess.run(["git", "-C", str(repo), *args], env=env, check=True, capture_output=True,
                          text=True).stdout.strip()


def caller_env(work: Path) -> dict[str, str]:
    """What a CI system or a calling script may have set for its own purposes: names the script read before it
    prefixed its settings, with values that would break it (OUT a file, an unknown task, a baseline elsewhere)."""
    return {"OUT": str(work / "caller-out.txt"), "TASKS": "NoSuchTask", "EPISODES": "many", "MAX_STEPS": "x",
            "BASELINE": str(work / "caller-baseline"), "BASELINE_MODEL": str(work / "no-such-model"),
            "BASELINE_ARGS": "--no-such-option", "FAIL_ON": "bogus", "OCTO_HARNESS": "false", "PYTHON": "false",
            "CANDIDATE": str(work / "no-such-model")}


def gate(candidate: str, cwd: Path, work: Path, **settings: str) -> subprocess.CompletedProcess:
    """The script as a CI job runs it, from the repository's root, with a small protocol and its OCTO_GATE_ settings."""
    harness = Path(sys.executable).with_name("octo-harness")
    env = {k: v for k, v in os.environ.items() if not k.startswith("OCTO_GATE_")}
    env.update(caller_env(work))
    env.update({"OCTO_GATE_TASKS": "Lift", "OCTO_GATE_EPISODES": "1", "OCTO_GATE_MAX_STEPS": "1",
                "OCTO_GATE_FAIL_ON": "changed", "OCTO_GATE_PYTHON": sys.executable,
                "OCTO_GATE_HARNESS": str(harness) if harness.exists() else "octo-harness"})
    env.update({f"OCTO_GATE_{k.upper()}": v for k, v in settings.items()})
    return subprocess.run(["bash", str(SCRIPT), candidate], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=600)


def checkpoint_of(model: Path) -> Path:
    return next(model.glob("*/default/checkpoint"))


def degrade(model: Path) -> None:
    """The checkpoint's action head kernels scaled by 1.5, in place: same architecture, other actions."""
    import flax.serialization as serialization

    path = checkpoint_of(model)
    tree = serialization.msgpack_restore(path.read_bytes())

    def scale(node):
        for key, value in node.items():
            if isinstance(value, dict):
                scale(value)
            elif key == "kernel":
                node[key] = (np.asarray(value) * 1.5).astype(value.dtype)

    scale(tree["heads_action"])
    path.write_bytes(serialization.msgpack_serialize(tree))


@pytest.fixture(scope="module")
def pull_request(fixtures_dir, tmp_path_factory):
    """A repository whose base commit holds the tiny fixture at models/policy, and a pull request that degrades it
    in place; then the gate's runs in the order a CI history makes them."""
    work = tmp_path_factory.mktemp("ci")
    (work / "caller-out.txt").write_text("the caller's file\n")
    repo = work / "repo"
    repo.mkdir()
    git(repo, "init", "-q", "-b", "main")
    shutil.copytree(fixtures_dir / "tiny", repo / MODEL)
    git(repo, "add", "models")
    git(repo, "commit", "-q", "-m", "base")
    base = git(repo, "rev-parse", "HEAD")
    degrade(repo / MODEL)
    git(repo, "commit", "-q", "-am", "the pull request: a new checkpoint in place")
    runs = {"base": base}
    # The baseline is missing (the cache is keyed on the base's checkpoint): the gate makes it from the base's version.
    runs["degraded"] = gate(MODEL, repo, work, base_rev=base, baseline_model=MODEL, out=str(work / "runs-degraded"))
    # The same path back as the base has it: an unchanged candidate, gated against the baseline made above.
    shutil.rmtree(repo / MODEL)
    shutil.copytree(fixtures_dir / "tiny", repo / MODEL)
    runs["unchanged"] = gate(MODEL, repo, work, base_rev=base, baseline_model=MODEL, out=str(work / "runs-unchanged"))
    # A damaged checkpoint in place: no verdict.
    checkpoint = checkpoint_of(repo / MODEL)
    checkpoint.write_bytes(checkpoint.read_bytes()[: checkpoint.stat().st_size // 2])
    runs["damaged"] = gate(MODEL, repo, work, base_rev=base, baseline_model=MODEL, out=str(work / "runs-damaged"))
    return work, repo, runs


def output(done: subprocess.CompletedProcess) -> str:
    return done.stdout[-3000:] + done.stderr[-3000:]


def test_a_candidate_degraded_in_place_fails_against_the_base(pull_request):
    work, repo, runs = pull_request
    done = runs["degraded"]
    assert done.returncode == 1, output(done)
    assert f"making it once from {MODEL} as at {runs['base']}" in done.stdout  # from the base, not the working tree
    tree = git(repo, "rev-parse", f"{runs['base']}:{MODEL}")
    assert f"tree {tree}" in done.stdout
    assert "CHANGED" in done.stdout and "gate: FAIL" in done.stdout
    assert re.search(r"gate: FAIL: .*/runs-degraded/[^/]+/regress/regress\.json\)$", done.stdout, re.M)
    # The default baseline folder, relative to where the job runs, is named by the base checkpoint's tree.
    assert f"baseline made at results/baselines/ci-{tree[:12]}" in done.stdout
    assert (repo / "results" / "baselines" / f"ci-{tree[:12]}" / "BASELINE.json").is_file()


def test_an_unchanged_candidate_passes_against_the_baseline_made_once(pull_request):
    _, _, runs = pull_request
    done = runs["unchanged"]
    assert done.returncode == 0, output(done)
    assert "making it once" not in done.stdout and "made earlier" in done.stdout
    assert "IDENTICAL" in done.stdout and "gate: PASS" in done.stdout


def test_a_damaged_candidate_gives_no_verdict(pull_request):
    _, _, runs = pull_request
    done = runs["damaged"]
    assert done.returncode == 2, output(done)
    assert "gate: ERROR: invalid input" in done.stderr
    assert "Traceback" not in done.stderr


def test_the_callers_generic_environment_names_have_no_effect(pull_request):
    work, repo, runs = pull_request
    assert (work / "caller-out.txt").read_text() == "the caller's file\n"  # OUT, a file, neither written nor refused
    assert not (work / "caller-baseline").exists()
    for name in ("degraded", "unchanged"):  # the candidate's runs went where OCTO_GATE_OUT says
        assert list((work / f"runs-{name}").glob("*/results.jsonl")), name
    for name in ("degraded", "unchanged", "damaged"):
        assert "NoSuchTask" not in output(runs[name]) and "no-such" not in output(runs[name]), name


def test_an_unknown_base_revision_gives_no_verdict_before_running_anything(pull_request, tmp_path):
    work, repo, _ = pull_request
    done = gate(MODEL, repo, work, base_rev="no-such-revision", baseline=str(tmp_path / "baseline"),
                baseline_model=MODEL, harness="false")  # octo-harness must not even start
    assert done.returncode == 2, output(done)
    assert "OCTO_GATE_BASE_REV=no-such-revision is not a commit" in done.stderr
    assert not (tmp_path / "baseline").exists()


def test_without_a_base_revision_a_candidate_at_the_baseline_models_path_is_named_as_gated_against_itself(
        pull_request, tmp_path):
    work, repo, _ = pull_request
    done = gate(MODEL, repo, work, baseline=str(tmp_path / "baseline"), baseline_model=MODEL, harness="false")
    assert f"making it once from {MODEL} in the working tree" in done.stdout
    assert "gates the candidate against itself; set OCTO_GATE_BASE_REV" in done.stderr
    assert done.returncode == 2  # `false` as octo-harness: the baseline cannot be made, no verdict


def test_a_crash_that_writes_no_verdict_is_no_verdict_not_a_fail(pull_request, tmp_path):
    """An uncaught Python error also exits 1: without the regress.json regress names, exit 1 is not read as FAIL."""
    work, repo, runs = pull_request
    crash = tmp_path / "octo-harness"
    crash.write_text("#!/bin/sh\necho 'Traceback (most recent call last):' >&2\nexit 1\n")
    crash.chmod(0o755)
    done = gate(MODEL, repo, work, base_rev=runs["base"], baseline_model=MODEL, harness=str(crash))
    assert done.returncode == 2, output(done)  # the baseline exists (made by the first gate): regress is called at once
    assert "made earlier" in done.stdout and "gate: FAIL" not in done.stdout
    assert "wrote no regress.json (a crash?), no verdict" in done.stderr


def workflow() -> dict:
    return yaml.safe_load(WORKFLOW.read_text())


def step(flow: dict, name: str) -> dict:
    return next(s for s in flow["jobs"]["gate"]["steps"] if s.get("name") == name or s.get("id") == name)


def test_the_workflow_runs_the_script_on_the_base_revision():
    flow = workflow()
    steps = flow["jobs"]["gate"]["steps"]
    checkout = next(s for s in steps if s.get("uses", "").startswith("actions/checkout"))
    assert checkout["with"]["fetch-depth"] == 0  # the base commit and the default branch are in the clone
    gate_step = step(flow, "Gate the candidate")
    assert gate_step["run"].strip().startswith("bash examples/ci/regress-gate.sh")
    assert gate_step["env"]["OCTO_GATE_BASE_REV"] == "${{ steps.base.outputs.rev }}"
    for name in ("OCTO_GATE_CANDIDATE", "OCTO_GATE_BASELINE_MODEL", "OCTO_GATE_BASELINE"):
        assert flow["env"][name], name
    for path in (flow["env"]["OCTO_GATE_CANDIDATE"], flow["env"]["OCTO_GATE_BASELINE_MODEL"]):
        assert (REPO / path / "config.json").is_file(), path  # the example's models exist in this repository
    # Every setting the workflow gives the script has the script's prefix (they are the script's documented settings).
    settings = set(re.findall(r"\b(OCTO_GATE_[A-Z_]+)=", SCRIPT.read_text()))
    given = {k for k in flow["env"] if k.startswith("OCTO_GATE_")} | set(gate_step["env"])
    assert given - {"OCTO_GATE_CANDIDATE"} <= settings, given - settings


def test_the_baseline_cache_is_keyed_on_the_base_checkpoint_never_on_the_candidates_files():
    flow = workflow()
    cache = next(s for s in flow["jobs"]["gate"]["steps"] if s.get("uses", "").startswith("actions/cache"))
    assert cache["with"]["path"] == "${{ env.OCTO_GATE_BASELINE }}"
    key = cache["with"]["key"]
    assert "${{ steps.base.outputs.tree }}" in key
    # hashFiles reads the pull request's working tree: only the harness's own pyproject.toml may be hashed.
    assert re.findall(r"hashFiles\(([^)]*)\)", key) == ["'pyproject.toml'"], key
    assert "CANDIDATE" not in key and "BASELINE_MODEL" not in key


@pytest.mark.parametrize("event", ["pull_request", "workflow_dispatch"])
def test_the_workflows_base_step_names_the_base_checkpoint_and_says_which(event, tmp_path):
    """The step's shell, run as Actions runs it, in a clone whose pull request changed the checkpoint in place:
    the tree it outputs (the cache key) is the base's, and one line says which base."""
    repo = tmp_path / "repo"
    repo.mkdir()
    git(repo, "init", "-q", "-b", "feature")
    (repo / MODEL).mkdir(parents=True)
    (repo / MODEL / "checkpoint").write_text("base")
    git(repo, "add", "models")
    git(repo, "commit", "-q", "-m", "base")
    base = git(repo, "rev-parse", "HEAD")
    git(repo, "update-ref", "refs/remotes/origin/main", base)  # the default branch, as a full checkout fetches it
    (repo / MODEL / "checkpoint").write_text("candidate")
    git(repo, "commit", "-q", "-am", "candidate in place")
    base_step = step(workflow(), "base")
    outputs = tmp_path / "github_output"
    env = {**os.environ, "GITHUB_OUTPUT": str(outputs), "OCTO_GATE_BASELINE_MODEL": MODEL,
           "PR_BASE_SHA": base if event == "pull_request" else "", "DEFAULT_BRANCH": "main"}
    assert set(base_step["env"]) == {"PR_BASE_SHA", "DEFAULT_BRANCH"}
    done = subprocess.run(["bash", "-c", base_step["run"]], cwd=repo, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    values = dict(line.split("=", 1) for line in outputs.read_text().splitlines())
    assert values == {"rev": base, "tree": git(repo, "rev-parse", f"{base}:{MODEL}")}
    assert values["tree"] != git(repo, "rev-parse", f"HEAD:{MODEL}")
    (line,) = [line for line in done.stdout.splitlines() if line.startswith("gate:")]
    assert ("pull request's base commit" if event == "pull_request" else "default branch main") in line

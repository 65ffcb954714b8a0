"""A clone stands alone (issue 71): nothing the tests, scripts or docs use lies outside the repository.

Two checks:
- every committed text file is free of absolute paths into a checkout (the repository's own folders, the
  reference fixtures) and of `../shared`, outside docs/history;
- representative tests (the Octo fixtures, the gate examples, the committed EVAL.md sections, one simulated
  episode of the tiny fixture) pass from a copy of the repository in a folder with nothing else in it, while
  tests/_path_audit.py records every file they open or list outside the repository, the Python installation, the
  system and the temporary folder. A canary test added to the copy reads ../shared, as the tests did before the
  fixtures moved in: the audit must name it, and nothing else.
"""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# An absolute path into a checkout's own folders, or the fixtures' old place beside it. A /tmp/ path is a command's
# own scratch folder (a `git worktree add /tmp/x` in a provenance line), never one machine's checkout.
CHECKOUT_PATH = re.compile(r"(?<![\w.~-])(?!/tmp/)/(?:[\w.+-]+/)+(?:tests/fixtures|models/octo-reference|results/baselines|"
                           r"shared/fixtures|scripts/\w+\.(?:sh|py))|\.\./shared/")
REPRESENTATIVE = ["tests/octo/test_param_tree.py::test_preset_matches_released_parameter_tree[octo-small-1.5]",
                  "tests/octo/test_errors.py", "tests/gate/test_result_schema.py",
                  "tests/docs/test_eval_sections.py",
                  "tests/rollout/test_episode_files.py::test_cli_runs_an_episode_and_rejects_an_unknown_task"]
CANARY = '''
from pathlib import Path

def test_reads_the_old_fixture_folder():
    old = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "octo-reference" / "README.md"
    try:
        old.read_text()
    except FileNotFoundError:
        pass
'''


def committed_files() -> list[str]:
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"], cwd=REPO,
                         capture_output=True, check=True).stdout
    return [p for p in out.decode().split("\0") if p and (REPO / p).is_file()]


def test_no_committed_file_names_a_checkout_path():
    offenders = []
    for name in committed_files():
        if name.startswith("docs/history/") or name == "tests/test_standalone.py":
            continue
        try:
            text = (REPO / name).read_text()
        except (UnicodeDecodeError, OSError):
            continue  # binary data: checkpoints, arrays, images
        offenders += [f"{name}: {m.group(0)}" for m in CHECKOUT_PATH.finditer(text)]
        if str(REPO) in text:
            offenders.append(f"{name}: {REPO}")
    assert not offenders, "absolute paths of one machine in committed files:\n" + "\n".join(offenders[:20])


def test_the_pattern_catches_what_it_is_for():
    for bad in ('"/work/main/models/octo-reference-robosuite"', '"/work/shared/fixtures/octo-reference/tiny"',
                "REPO.parent / '../shared/fixtures'", "/home/u/octo-harness/results/baselines/reference-lift"):
        assert CHECKOUT_PATH.search(bad), bad
    for fine in ('"models/octo-reference-robosuite"', "tests/fixtures/octo-reference/tiny", "--out /shared/runs"):
        assert not CHECKOUT_PATH.search(fine), fine


@pytest.mark.slow
def test_representative_tests_pass_from_a_copy_with_nothing_beside_it(tmp_path):
    copy = tmp_path / "alone" / "octo-harness"
    for name in committed_files():
        (copy / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / name, copy / name)
    (copy / "tests" / "test_zz_canary.py").write_text(CANARY)
    log = tmp_path / "audit.json"
    env = {k: v for k, v in os.environ.items() if k not in ("OCTO_REFERENCE_FIXTURES", "PYTEST_XDIST_WORKER",
                                                             "PYTEST_CURRENT_TEST", "PYTHONPYCACHEPREFIX")}
    # the suite's XLA compilation cache (tests/conftest.py) is shared, as a speed-up the audit allows, never an input
    env.update(OCTO_AUDIT_ROOT=str(copy), OCTO_AUDIT_LOG=str(log), HF_HUB_OFFLINE="1",
               OCTO_AUDIT_ALLOW=os.environ.get("JAX_COMPILATION_CACHE_DIR", ""))
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "no:cacheprovider",
                           "-p", "tests._path_audit", *REPRESENTATIVE, "tests/test_zz_canary.py"],
                          cwd=copy, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert re.search(r"\b\d+ passed\b", proc.stdout) and " skipped" not in proc.stdout, proc.stdout[-2000:]
    outside = json.loads(log.read_text())
    canary = {p: t for p, t in outside.items() if "test_zz_canary" in t}
    assert any(p.endswith("shared/fixtures/octo-reference/README.md") for p in canary), outside
    others = {p: t for p, t in outside.items() if p not in canary}
    assert not others, f"tests read outside the repository: {others}"

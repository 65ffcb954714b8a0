"""The commit a run records (manifest `harness.commit`): read from .git in a plain checkout, a worktree (whose .git
is a file) and a detached HEAD, with packed refs; None outside a checkout."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from harness.runfolder.platform import git_commit

pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def _git(cwd, *args) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True,
                          env={"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
                               "GIT_COMMITTER_EMAIL": "t@t", "HOME": str(cwd), "PATH": "/usr/bin:/bin"}).stdout.strip()


def test_the_commit_is_read_in_a_checkout_a_worktree_and_a_detached_head(tmp_path):
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q", "-b", "main")
    (repo / "f").write_text("1")
    _git(repo, "add", "f")
    _git(repo, "commit", "-qm", "one")
    first = _git(repo, "rev-parse", "HEAD")
    assert git_commit(repo) == first
    _git(repo, "worktree", "add", "-q", "-b", "side", str(tmp_path / "wt"))
    (tmp_path / "wt" / "f").write_text("2")
    _git(tmp_path / "wt", "commit", "-qam", "two")
    second = _git(tmp_path / "wt", "rev-parse", "HEAD")
    assert (tmp_path / "wt" / ".git").is_file() and git_commit(tmp_path / "wt") == second != first
    _git(repo, "pack-refs", "--all")  # refs only in packed-refs, read through the worktree's commondir
    assert git_commit(tmp_path / "wt") == second and git_commit(repo) == first
    _git(repo, "worktree", "add", "-q", "--detach", str(tmp_path / "detached"), first)
    assert git_commit(tmp_path / "detached") == first
    assert git_commit(tmp_path / "nowhere") is None

"""A FIFO, a device or a socket where a command reads a file (issue 66): named as "not a regular file" from its
`stat`, never opened (a FIFO would block the command), by the bounded reader every command reads through
(harness/bounded.py) and by the run folder's own check (harness/runfolder/integrity.py); and rows the user may not
read, named too. The commands' answers (exit 2, one line) are cases of the hostile-file corpus
(tests/runfolder/hostile_corpus.py)."""

from __future__ import annotations

import os
import shutil
import socket
import stat
import tempfile
import threading
from pathlib import Path

import pytest

from harness.analysis.runs import load_run
from harness.bounded import BoundsError, npz_headers, read_json, read_jsonl_text, read_toml
from harness.runfolder.schema import MalformedRunError

BASELINE = Path(__file__).resolve().parents[2] / "results" / "baselines" / "reference-lift"


def answer(call, *args):
    """What `call(*args)` raised, from a thread given 20 s (a read that blocks on a FIFO fails the test, not hangs)."""
    raised: list[BaseException] = []

    def target():
        try:
            call(*args)
        except BaseException as exc:  # noqa: BLE001 - the test looks at it
            raised.append(exc)

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(20)
    assert not thread.is_alive(), f"{call.__name__} blocked on {args[0]}"
    assert raised, f"{call.__name__} read {args[0]}"
    return raised[0]


def special(path: Path, kind: str) -> None:
    if kind == "FIFO":
        os.mkfifo(path)
    elif kind == "character device":
        try:
            os.mknod(path, 0o600 | stat.S_IFCHR, os.makedev(1, 3))  # a /dev/null
        except PermissionError:
            pytest.skip("this user may not make a device")
    else:
        with socket.socket(socket.AF_UNIX) as s:
            s.bind(str(path))


@pytest.mark.parametrize("kind", ["FIFO", "character device", "socket"])
def test_the_bounded_readers_name_a_file_that_is_not_regular_and_never_block(tmp_path, kind):
    for name, read in (("x.json", read_json), ("x.jsonl", read_jsonl_text), ("x.toml", read_toml),
                       ("x.npz", npz_headers)):
        special(tmp_path / name, kind)
        raised = answer(read, tmp_path / name)
        assert isinstance(raised, BoundsError) and f"is not a regular file (it is a {kind})" in str(raised), raised


def test_a_folder_in_a_files_place_stays_an_os_error(tmp_path):
    (tmp_path / "x.json").mkdir()
    assert isinstance(answer(read_json, tmp_path / "x.json"), IsADirectoryError)


@pytest.mark.parametrize("name", ["results.jsonl", "manifest.json", "results.json"])
def test_a_run_file_that_is_a_fifo_is_named_not_read_as_missing(tmp_path, name):
    run = tmp_path / "run"
    shutil.copytree(BASELINE, run)
    (run / name).unlink()
    os.mkfifo(run / name)
    raised = answer(load_run, run)
    assert isinstance(raised, MalformedRunError), raised
    assert f"{run / name} is not a regular file (it is a FIFO)" in str(raised)


def test_rows_this_user_may_not_read_are_named(tmp_path):
    """An unreadable results.jsonl is a PermissionError naming it (the command line: exit 2, one line). Root reads
    any file, so as root the read runs in a child that became `nobody`."""
    folder = Path(tempfile.mkdtemp(prefix="unreadable-"))  # outside pytest's 0700 tree: `nobody` must reach it
    try:
        os.chmod(folder, 0o755)
        run = folder / "run"
        shutil.copytree(BASELINE, run)
        os.chmod(run / "results.jsonl", 0)
        read, write = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: load the run as a user who may not read the rows, say what was raised
            try:
                if os.geteuid() == 0:
                    os.setgroups([])
                    os.setgid(65534)
                    os.setuid(65534)
            except OSError as exc:
                said = f"skip: cannot become nobody ({exc})"
            else:
                try:
                    load_run(run)
                    said = "read"
                except BaseException as exc:  # noqa: BLE001 - reported to the parent
                    said = f"{type(exc).__name__}: {exc}"
            os.write(write, said.encode()[:4000])
            os._exit(0)
        os.close(write)
        with os.fdopen(read, "rb") as pipe:
            said = pipe.read().decode()
        os.waitpid(pid, 0)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    if said.startswith("skip: "):
        pytest.skip(said[6:])
    assert said.startswith("PermissionError") and str(run / "results.jsonl") in said, said

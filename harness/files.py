"""Atomic file writing: every product file goes to a temp file in the same folder, then os.replace.

A crash or Ctrl-C therefore never leaves a half-written file under its final name; a temp file is
`<name>.tmp.<pid>.<ext>` (unique per process, so two processes never share one; the extension stays last so
encoders such as ffmpeg pick the format) and is deleted when its write fails. Leftovers of a killed process
match `*.tmp.*`; a resumed run deletes them. JSON files go through `json_safe` (numpy values to Python, NaN/inf to null).
"""

from __future__ import annotations

import json
import math
import os
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any, Callable

import numpy as np

# the folder beside a model's EVAL.md that holds its sections' figures files (harness/report/figures_file.py): results
# about a checkpoint, not part of it, so a model's fingerprint leaves it out (harness/run/protocol.checkpoint_files)
FIGURES_FOLDER = "figures"


def temp_path(path: Path) -> Path:
    """`dir/name.ext` -> `dir/name.tmp.<pid>.ext` (pid of this process)."""
    return path.with_name(f"{path.stem}.tmp.{os.getpid()}{path.suffix}")


class _Settled:
    """A file handed to a writer callback; once the callback is over (it returned or raised), the writer objects it
    leaves behind can no longer touch it. np.savez leaves its ZipFile unclosed when a write fails (a full disk);
    the ZipFile's __del__ later closes it, writing to the closed file, and Python printed a 7-line "Exception
    ignored in ZipFile.__del__" trace beside the command's own one-line error. After `settle()` every call is a
    harmless no-op."""

    def __init__(self, f: IO[bytes]):
        self._f, self._settled, self._pos = f, False, 0

    def settle(self) -> None:
        try:
            self._pos = self._f.tell()
        except (OSError, ValueError):
            pass
        self._settled = True

    def write(self, data) -> int:
        return len(data) if self._settled else self._f.write(data)

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._pos if self._settled else self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._pos if self._settled else self._f.tell()

    def flush(self) -> None:
        if not self._settled:
            self._f.flush()

    def __getattr__(self, name):
        return getattr(self._f, name)


def write_atomic(path: str | Path, write: Callable[[IO[bytes]], None]) -> Path:
    """Call `write(file)` on `<name>.tmp.<pid>.<ext>` in the same directory, then os.replace it onto `path`.
    What `write` leaves behind holding the file (an unclosed ZipFile after a full disk) cannot write to it later."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(path)
    try:
        with open(tmp, "wb") as f:
            handle = _Settled(f)
            try:
                write(handle)
            finally:
                handle.settle()
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


@contextmanager
def all_or_none(*paths: str | Path):
    """Files written together as one result (compare.json, compare.md, compare.html): when the block fails (a full
    disk), every one of them is removed, so a folder never holds part of a result beside files of an older one."""
    try:
        yield
    except BaseException:
        for path in paths:
            Path(path).unlink(missing_ok=True)
        raise


def atomic_write_json(path: str | Path, obj, exact: bool = False) -> Path:
    """`json_safe(obj)` as indented JSON with sorted keys, written atomically. `exact` keeps every float digit (and
    writes other objects as strings): for summaries whose configuration is compared on reuse."""
    body = json.dumps(obj, indent=2, sort_keys=True, default=str) if exact else \
        json.dumps(json_safe(obj), indent=2, sort_keys=True)
    return write_atomic(path, lambda f: f.write((body + "\n").encode()))


def read_json_object(path: str | Path) -> dict | None:
    """The JSON object in `path`, or None when it is missing, torn, not UTF-8 or not an object (a stale or edited
    summary then reads as "nothing finished here" rather than a traceback)."""
    try:
        obj = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return obj if isinstance(obj, dict) else None


def replace_markdown_section(path: str | Path, heading: str, section: str) -> Path:
    """Replace the `heading` section ("## Name" up to the next "## ") of the Markdown file `path` with `section` (which
    starts with that heading), or append it; every other section stays as it is. Written atomically."""
    path = Path(path)
    text = path.read_text() if path.is_file() else ""
    head, _, rest = text.partition("\n" + heading + "\n")
    after = "\n## " + rest.split("\n## ", 1)[1] if rest and "\n## " in rest else ""
    data = (head.rstrip("\n") + "\n\n" + section + after).encode()
    return write_atomic(path, lambda f: f.write(data))


def json_safe(x: Any) -> Any:
    """JSON-safe copy: numpy scalars/arrays and Paths to Python, NaN/inf to None, floats rounded to 6 places (6 significant digits below 1)."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        if not math.isfinite(x):
            return None
        return round(x, 6) if abs(x) >= 1 else float(f"{x:.6g}")  # 6 significant digits below 1 (1e-9 stays 1e-9)
    if isinstance(x, Path):
        return str(x)
    return x

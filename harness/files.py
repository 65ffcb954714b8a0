"""Atomic file writing: every product file goes to a temp file in the same folder, then os.replace.

A crash or Ctrl-C therefore never leaves a half-written file under its final name; a temp file is
`<name>.tmp.<ext>` (the extension stays last so encoders such as ffmpeg pick the format) and is
deleted when its write fails.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import IO, Callable

import numpy as np


def temp_path(path: Path) -> Path:
    """`dir/name.ext` -> `dir/name.tmp.ext`."""
    return path.with_name(f"{path.stem}.tmp{path.suffix}")


def write_atomic(path: str | Path, write: Callable[[IO[bytes]], None]) -> Path:
    """Call `write(file)` on `<name>.tmp.<ext>` in the same directory, then os.replace it onto `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(path)
    try:
        with open(tmp, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def atomic_write_json(path: str | Path, obj) -> Path:
    data = (json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n").encode()
    return write_atomic(path, lambda f: f.write(data))


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")

"""Bounded reading: the one way a command reads a file it did not just write (run folders, checkpoints, protocol files,
grid files), so a hostile or damaged file is one line and exit 2 in bounded time and memory, never a traceback.

- Size: `stat` before `read`; a file over its kind's limit is refused unread (a 20 GB sparse manifest.json costs
  one stat).
- Kind: only a regular file is read. A FIFO, a device or a socket in a file's place is refused from its `stat`,
  never opened for reading (a FIFO would block the command, a device would read forever or read as empty).
- Nesting: JSON and TOML documents are scanned for their bracket depth before they are parsed (numpy over the
  bytes with the strings blanked, no recursion), so `[[[[...` 10^5 deep is refused before the recursive parsers
  see it; a RecursionError the scan missed is caught here too.
- Arrays: a `.npz` member's shape and dtype are read from its `.npy` header inside the zip (a few hundred bytes
  decompressed) and checked, with the zip entry's size, against the caller's expectations and a byte budget before
  any data is loaded (`npz_headers`, `check_npz`, `read_npz`), so a 2 MB archive that expands to gigabytes is
  refused unread.

Every violation is a `BoundsError` (a ValueError: the command line prints one line, exit 2) naming the file and
the limit. The limits are stated in docs/run-integrity.md.
"""

from __future__ import annotations

import errno
import json
import os
import re
import stat
import zipfile
from typing import Any, Iterable, Mapping

import numpy as np

MiB = 1 << 20
MAX_JSON_BYTES = 64 * MiB  # manifest.json, results.json, episode.json, robustness.json, config.json, statistics
MAX_JSONL_BYTES = 512 * MiB  # results.jsonl, metrics.jsonl, faithfulness.jsonl (100000 rows of a few kB)
MAX_TOML_BYTES = 1 * MiB  # protocol files, a checkpoint's harness.toml
MAX_TEXT_BYTES = 16 * MiB  # other text a command reads (a tokenizer.json is larger: MAX_JSON_BYTES)
MAX_DEPTH = 64  # nesting of [ and { in a JSON or TOML document (the run store's deepest is 5)
MAX_NPZ_BYTES = 8 << 30  # what the arrays of one .npz may hold once loaded, whatever the caller expects
MAX_STEP_BYTES = 16 * MiB  # what one step of one array may hold (a 2048 px camera frame is 12 MiB)
MAX_NPZ_MEMBERS = 10_000
CUT = 200  # characters of a bad value echoed in a one-line error


class BoundsError(ValueError):
    """A file over a stated limit (size, nesting depth, array shape): one line naming the file and the limit."""


def short(value: Any, limit: int = CUT) -> str:
    """repr(value) cut to about `limit` characters (a 50 MB bad value is never echoed whole); a cut string says its
    length."""
    if isinstance(value, str):
        text = repr(value[: limit + 1])
        return text if len(value) <= limit else f"{text[: limit - 3]}... ({len(value)} characters)"
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _mib(n: int) -> str:
    return f"{n / MiB:.0f} MiB" if n >= MiB else f"{n} bytes"


_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def file_kind(mode: int) -> str | None:
    """None for a regular file, else what the `stat` mode says it is ("a FIFO", "a character device", ...)."""
    if stat.S_ISREG(mode):
        return None
    return next((name for test, name in _KINDS if test(mode)), "not a plain file")


def check_regular(path: str | os.PathLike, st: os.stat_result | None = None, what: str = "file") -> os.stat_result:
    """`path`'s stat (links followed), or BoundsError when it is not a regular file (FileNotFoundError passes; a
    folder is IsADirectoryError, as `open` says)."""
    st = os.stat(path) if st is None else st
    if stat.S_ISDIR(st.st_mode):
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
    kind = file_kind(st.st_mode)
    if kind is not None:
        raise BoundsError(f"{path} is not a regular file (it is {kind}); a {what} is read only from a plain file: "
                          "put the file itself there (docs/run-integrity.md#bounded-reading)")
    return st


def check_size(path: str | os.PathLike, limit: int, what: str = "file") -> int:
    """The file's size from `stat`, or BoundsError when it exceeds `limit` or is not a regular file
    (FileNotFoundError passes through)."""
    size = check_regular(path, what=what).st_size
    if size > limit:
        raise BoundsError(f"{path} is {size} bytes, over the {_mib(limit)} a {what} may hold; it is damaged or not "
                          "what it claims to be (docs/run-integrity.md#bounded-reading)")
    return size


def read_bytes(path: str | os.PathLike, limit: int = MAX_TEXT_BYTES, what: str = "file") -> bytes:
    """The file's bytes, at most `limit` (checked by stat first; a file that grows while read is cut at the limit
    and refused). Only a regular file is opened; one swapped for a FIFO after the stat is opened without blocking
    and refused unread."""
    check_size(path, limit, what)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    with open(fd, "rb") as f:
        check_regular(path, os.fstat(fd), what)
        data = f.read(limit + 1)
    if len(data) > limit:
        raise BoundsError(f"{path} grew over the {_mib(limit)} a {what} may hold while it was read")
    return data


def read_text(path: str | os.PathLike, limit: int = MAX_TEXT_BYTES, what: str = "file", errors: str = "strict") -> str:
    return read_bytes(path, limit, what).decode("utf-8", errors=errors)


_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)
_TOML_STRING = re.compile(rb'"""(?:[^\\]|\\.)*?"""|\'\'\'.*?\'\'\'|"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\'', re.DOTALL)
_TOML_COMMENT = re.compile(rb"#[^\n]*")


def nesting_depth(data: bytes | str, toml: bool = False) -> int:
    """Largest depth of [ and { in a JSON (or TOML) text, strings (and TOML comments) left out; no recursion."""
    raw = data.encode() if isinstance(data, str) else data
    raw = _JSON_STRING.sub(b'""', raw) if not toml else _TOML_COMMENT.sub(b"", _TOML_STRING.sub(b'""', raw))
    if not raw:
        return 0
    arr = np.frombuffer(raw, dtype=np.uint8)
    step = ((arr == ord("[")) | (arr == ord("{"))).astype(np.int64) - ((arr == ord("]")) | (arr == ord("}")))
    depth = np.cumsum(step)
    return int(depth.max()) if depth.size else 0


def check_depth(data: bytes | str, where: str, toml: bool = False, limit: int = MAX_DEPTH) -> None:
    depth = nesting_depth(data, toml)
    if depth > limit:
        raise BoundsError(f"{where} nests {depth} levels deep, over the {limit} a document may nest; it is damaged "
                          "or not what it claims to be (docs/run-integrity.md#bounded-reading)")


def loads_json(data: bytes | str, where: str, limit: int = MAX_DEPTH) -> Any:
    """json.loads after the depth check; a JSON error stays a ValueError (json.JSONDecodeError) for the caller."""
    check_depth(data, where, limit=limit)
    try:
        return json.loads(data)
    except RecursionError:
        raise BoundsError(f"{where} nests too deep to parse (limit {limit})") from None


def read_json(path: str | os.PathLike, limit: int = MAX_JSON_BYTES, what: str = "JSON file") -> Any:
    """A JSON file, size and depth checked; invalid JSON is a ValueError (json.JSONDecodeError) for the caller."""
    return loads_json(read_bytes(path, limit, what), str(path))


def read_jsonl_text(path: str | os.PathLike, limit: int = MAX_JSONL_BYTES, errors: str = "replace") -> str:
    """A JSON-lines file's text, size and depth checked (rows are parsed by the caller, line by line)."""
    data = read_bytes(path, limit, "JSON-lines file")
    check_depth(data, str(path))
    return data.decode("utf-8", errors=errors)


def read_toml(path: str | os.PathLike, limit: int = MAX_TOML_BYTES) -> dict:
    """A TOML file, size and depth checked; tomllib's own errors (TOMLDecodeError, UnicodeDecodeError) pass."""
    return loads_toml(read_bytes(path, limit, "TOML file").decode(), str(path))


def loads_toml(text: str, where: str) -> dict:
    import tomllib

    check_depth(text, where, toml=True)
    try:
        return tomllib.loads(text)
    except RecursionError:
        raise BoundsError(f"{where} nests too deep to parse (limit {MAX_DEPTH})") from None


# ---- .npz headers -------------------------------------------------------------------------------------------------

def npz_headers(path: str | os.PathLike) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """{member name (without .npy): (shape, dtype)} from the `.npy` headers inside a .npz, no data loaded. A member
    whose header is not a plain array's, whose zip entry is not the size its header implies, or an archive over
    MAX_NPZ_MEMBERS / MAX_NPZ_BYTES is a BoundsError; a file that is not a zip is zipfile.BadZipFile."""
    from numpy.lib import format as npformat

    out: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
    total = 0
    check_regular(path, what="array file")  # a FIFO is never opened (zipfile and np.load would block on it)
    with zipfile.ZipFile(path) as archive:
        infos = archive.infolist()
        if len(infos) > MAX_NPZ_MEMBERS:
            raise BoundsError(f"{path} holds {len(infos)} arrays, over the {MAX_NPZ_MEMBERS} an array file may hold")
        for info in infos:
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            with archive.open(info) as member:
                try:
                    version = npformat.read_magic(member)
                    if version == (1, 0):
                        shape, fortran, dtype = npformat.read_array_header_1_0(member, max_header_size=10_000)
                    elif version in ((2, 0), (3, 0)):
                        shape, fortran, dtype = npformat.read_array_header_2_0(member, max_header_size=10_000)
                    else:
                        raise ValueError(f"format version {version}")
                except (ValueError, EOFError, OSError) as exc:
                    raise BoundsError(f"{path}: {name} has no readable array header ({str(exc).splitlines()[0][:CUT]})"
                                      ) from None
                offset = member.tell()
            if dtype.hasobject:
                raise BoundsError(f"{path}: {name} holds Python objects ({dtype}); array files hold numbers and text only")
            nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if info.file_size != offset + nbytes:
                raise BoundsError(f"{path}: {name}'s header says {tuple(shape)} {dtype} ({nbytes} bytes) but its zip "
                                  f"entry holds {info.file_size - offset}; the file is damaged")
            total += nbytes
            if total > MAX_NPZ_BYTES:
                raise BoundsError(f"{path} expands to over {_mib(MAX_NPZ_BYTES)} of arrays, over what an array file "
                                  "may hold (docs/run-integrity.md#bounded-reading)")
            out[name] = (tuple(int(n) for n in shape), dtype)
    return out


STATIC_MEMBERS = ("seed", "instruction", "phase_names")  # array members with no step axis (and tokens/*, *_names)
MAX_STATIC_BYTES = 16 * MiB  # what one such member may hold


def _per_step(name: str) -> bool:
    return not (name in STATIC_MEMBERS or name.startswith("tokens/") or name.endswith("_names"))


def check_npz(path: str | os.PathLike, steps: int | None = None, axes: Mapping[str, Mapping[int, int]] | None = None,
              headers: Mapping[str, tuple[tuple[int, ...], np.dtype]] | None = None) -> dict:
    """The headers of `path` checked against what its episode implies: `steps` (the row's step count: no per-step
    array has more rows than steps, no step of one holds more than MAX_STEP_BYTES, no other member more than
    MAX_STATIC_BYTES) and `axes` ({member: {axis: size}}, e.g. {"readout_attention": {1: layers}}). Returns the
    headers; BoundsError names the member and the limit."""
    headers = npz_headers(path) if headers is None else headers
    for name, (shape, dtype) in headers.items():
        nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
        if not _per_step(name) or not shape:
            if nbytes > MAX_STATIC_BYTES:
                raise BoundsError(f"{path}: {name} holds {nbytes} bytes ({shape} {dtype}), over the "
                                  f"{_mib(MAX_STATIC_BYTES)} such a member may hold")
        elif steps is not None:
            if shape[0] > max(steps, 1):
                raise BoundsError(f"{path}: {name} holds {shape[0]} steps, but its row records {steps}; the file is "
                                  "damaged or not this episode's")
            per_step = nbytes // max(shape[0], 1)
            if per_step > MAX_STEP_BYTES:
                raise BoundsError(f"{path}: {name} holds {per_step} bytes per step ({shape} {dtype}), over the "
                                  f"{_mib(MAX_STEP_BYTES)} a step may hold")
        for axis, size in ((axes or {}).get(name) or {}).items():
            if len(shape) <= axis or shape[axis] != size:
                raise BoundsError(f"{path}: {name} has shape {shape}, but the run's manifest implies {size} along axis "
                                  f"{axis}; the file is damaged or not this run's")
    return dict(headers)


def read_npz(path: str | os.PathLike, names: Iterable[str] = (), steps: int | None = None,
             axes: Mapping[str, Mapping[int, int]] | None = None) -> dict[str, np.ndarray]:
    """{name: array} of a .npz (only `names` when given), its headers checked first (`check_npz`); no pickles."""
    headers = check_npz(path, steps, axes)
    wanted = list(names) or list(headers)
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in wanted}


def open_npz(path: str | os.PathLike, steps: int | None = None, axes: Mapping[str, Mapping[int, int]] | None = None):
    """np.load of a .npz (lazy: members load when indexed), its headers checked first (`check_npz`); no pickles."""
    check_npz(path, steps, axes)
    return np.load(path, allow_pickle=False)

"""The LIBERO env server's message format: nested data with numpy arrays over a byte stream (pure numpy + json).

One message = 8-byte big-endian header length, a JSON header, then the raw bytes of every array in order.
The header holds the data with each array replaced by {"__array__": i, "dtype": str, "shape": [...]}; arrays
are C-contiguous little-endian copies, so both sides of the pipe may run different numpy versions (no pickle:
the two processes live in two Python environments). Values allowed: dict (str keys), list/tuple (as lists),
str, int, float, bool, None and numpy arrays or scalars.

    write_message(stream, {"op": "step", "action": np.zeros(7)})
    message = read_message(stream)   # EOFError when the other side closed the stream

This file is imported by the driver (`envs.libero_wire`) and by the server (as a sibling module), so it imports
nothing from the harness.
"""

from __future__ import annotations

import json
import select
import struct
import time

import numpy as np

_HEADER = struct.Struct(">Q")
MAX_HEADER_BYTES = 64 << 20  # a header above this is a corrupt stream, not a message


def _encode(value, buffers: list) -> object:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        array = np.ascontiguousarray(value)
        if array.dtype.hasobject:
            raise TypeError("object arrays cannot cross the LIBERO process boundary")
        array = array.astype(array.dtype.newbyteorder("<"), copy=False)
        buffers.append(array.tobytes())
        return {"__array__": len(buffers) - 1, "dtype": array.dtype.str, "shape": list(array.shape)}
    if isinstance(value, dict):
        if "__array__" in value:
            raise ValueError("the key '__array__' is reserved by the wire format")
        return {str(k): _encode(v, buffers) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_encode(v, buffers) for v in value]
    if value is None or isinstance(value, (str, bool, int, float)):
        return value
    raise TypeError(f"cannot send {type(value).__name__} across the LIBERO process boundary")


def _decode(value, arrays: list):
    if isinstance(value, dict):
        if "__array__" in value:
            return arrays[value["__array__"]]
        return {k: _decode(v, arrays) for k, v in value.items()}
    if isinstance(value, list):
        return [_decode(v, arrays) for v in value]
    return value


def encode_message(data) -> bytes:
    """data -> one message's bytes."""
    buffers: list[bytes] = []
    tree = _encode(data, buffers)
    header = json.dumps({"data": tree, "sizes": [len(b) for b in buffers]}, separators=(",", ":")).encode()
    return _HEADER.pack(len(header)) + header + b"".join(buffers)


def write_message(stream, data) -> None:
    """Send one message on a binary stream and flush it. On an unbuffered stream (the server's) one write may take
    only part of the bytes (a pipe write interrupted by a signal or a stop, as a debugger's or `kill -STOP`'s): the
    rest is written until none is left, or the reader would wait forever for bytes never sent."""
    view = memoryview(encode_message(data))
    while view:
        written = stream.write(view)
        if written is None:  # a non-blocking stream that took nothing: never ours, but never loop on it
            raise BlockingIOError("the LIBERO pipe is non-blocking and full")
        view = view[written:]
    stream.flush()


class _WaitBudget:
    """Seconds this process may still wait for the other side. Waits run in slices of at most `SLICE` s, and a slice
    counts only up to its own length: time beyond it is this process not running (stopped with Ctrl-Z or SIGSTOP, a
    suspended job, a paused container), which says nothing about the other side, so resuming after a long stop
    does not read as a hung server."""
    SLICE = 1.0

    def __init__(self, seconds: float):
        self.left = seconds

    def wait_readable(self, stream) -> bool:
        while self.left > 0:
            step = min(self.SLICE, self.left)
            start = time.monotonic()
            ready, _, _ = select.select([stream], [], [], step)
            self.left -= min(time.monotonic() - start, step)
            if ready:
                return True
        return False


def _read_exact(stream, size: int, budget: _WaitBudget | None = None) -> bytes:
    chunks, left = [], size
    while left > 0:
        if budget is not None and not budget.wait_readable(stream):  # an unbuffered stream: select sees every byte
            raise TimeoutError("the other side of the LIBERO pipe sent nothing in time")
        chunk = stream.read(left)
        if not chunk:
            raise EOFError("the other side of the LIBERO pipe closed")
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def read_message(stream, timeout: float | None = None):
    """Receive one message from a binary stream; EOFError if it closed, ValueError if it is corrupt. With `timeout`
    (seconds of waiting for the whole message while this process runs; `stream` must then be unbuffered, such as a
    pipe opened with bufsize=0), TimeoutError when it has not all arrived by then."""
    budget = None if timeout is None else _WaitBudget(timeout)
    (length,) = _HEADER.unpack(_read_exact(stream, _HEADER.size, budget))
    if length > MAX_HEADER_BYTES:
        raise ValueError(f"LIBERO message header of {length} bytes: the stream is corrupt")
    header = json.loads(_read_exact(stream, length, budget))
    arrays = []
    specs: list = []
    _array_specs(header["data"], specs)
    specs.sort(key=lambda s: s["__array__"])
    if [s["__array__"] for s in specs] != list(range(len(header["sizes"]))):
        raise ValueError("LIBERO message: array references do not match its buffers")
    for spec, size in zip(specs, header["sizes"]):
        raw = _read_exact(stream, size, budget)
        dtype = np.dtype(spec["dtype"])
        array = np.frombuffer(raw, dtype=dtype).reshape(spec["shape"])
        arrays.append(array.astype(dtype.newbyteorder("="), copy=True))
    return _decode(header["data"], arrays)


def _array_specs(tree, out: list) -> None:
    if isinstance(tree, dict):
        if "__array__" in tree:
            out.append(tree)
            return
        for v in tree.values():
            _array_specs(v, out)
    elif isinstance(tree, list):
        for v in tree:
            _array_specs(v, out)

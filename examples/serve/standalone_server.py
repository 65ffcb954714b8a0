"""Serve ANY policy over openpi's websocket protocol, so `octo-harness run --model ws://HOST:PORT` can evaluate it.

Standalone: numpy, msgpack and websockets only (no harness, no openpi), so it runs in the policy's own environment
(the original Octo's, a JAX or PyTorch project's). The policy is any object with `infer(observation: dict) ->
{"actions": (action_horizon, action_dim) array}` and, optionally, a `metadata` dict (its "fingerprint" and "name"
identify it in the harness's runs). The protocol, as openpi's own server speaks it: on connect one binary frame with
the metadata; then one reply per observation frame; an error is sent as a text frame (the error, then its
traceback) and closes that connection only. Frames are msgpack with numpy arrays in openpi-client's encoding.

    python examples/serve/standalone_server.py --port 8000                         # the blind scripted Lift expert
    python examples/serve/standalone_server.py --policy my_module:MyPolicy --port 8000

`--policy MODULE:CLASS` (or FILE.py:CLASS) names the class, built with no arguments; the folder of this file is on
the import path, so `scripted_lift:BlindLiftExpert` (the default) is found. See docs/serving.md.
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import errno
import importlib
import importlib.util
import signal
import socket
import sys
import traceback
from pathlib import Path

import msgpack
import numpy as np

MAX_FRAME = 64 * 2 ** 20  # bytes of one incoming frame
REFUSED_KINDS = ("V", "O", "c")  # void, object and complex dtypes have no safe byte form


# ---- the codec: openpi-client's msgpack_numpy format, byte for byte --------------------------------------------

def _pack(obj):
    if isinstance(obj, (np.ndarray, np.generic)) and obj.dtype.kind in REFUSED_KINDS:
        raise ValueError(f"cannot send an array of dtype {obj.dtype}")
    if isinstance(obj, np.ndarray):
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    return obj


def _unpack(obj: dict):
    if b"__ndarray__" in obj or b"__npgeneric__" in obj:
        dtype = np.dtype(obj[b"dtype"])
        if dtype.kind in REFUSED_KINDS:
            raise ValueError(f"arrays of dtype {dtype} are refused")
        if b"__npgeneric__" in obj:
            return dtype.type(obj[b"data"])
        return np.ndarray(buffer=obj[b"data"], dtype=dtype, shape=tuple(obj[b"shape"]))
    return obj


def packb(obj) -> bytes:
    return msgpack.packb(obj, default=_pack)


def unpackb(data: bytes):
    return msgpack.unpackb(data, object_hook=_unpack)


# ---- the server -------------------------------------------------------------------------------------------------

def error_text(exc: BaseException) -> str:
    return " ".join(f"{type(exc).__name__}: {exc}".split())[:1000] + "\n" + "".join(traceback.format_exception(exc))


def answer(policy, message) -> bytes:
    """One frame -> its reply's bytes; raises on a frame or a reply that breaks the protocol."""
    if isinstance(message, str):
        raise ValueError("text frames are not requests; send msgpack in a binary frame")
    observation = unpackb(message)
    if not isinstance(observation, dict):
        raise ValueError(f"a frame must be a map (an observation), got {type(observation).__name__}")
    reply = policy.infer(observation)
    if not isinstance(reply, dict) or "actions" not in reply:
        raise TypeError(f"{type(policy).__name__}.infer must return a dict with 'actions', got {type(reply).__name__}")
    return packb({**reply, "actions": np.asarray(reply["actions"], np.float32)})


async def serve(policy, sock: socket.socket, ready=None) -> None:
    """Serve `policy` on a bound socket until SIGINT or SIGTERM; `ready(url)` once it listens. One worker thread
    calls the policy, one frame at a time."""
    from websockets.asyncio.server import serve as websocket_server
    from websockets.exceptions import ConnectionClosed

    loop, stop = asyncio.get_running_loop(), asyncio.Event()
    worker = concurrent.futures.ThreadPoolExecutor(1)
    metadata = packb(dict(getattr(policy, "metadata", None) or {}))
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)

    async def handle(connection) -> None:
        try:
            await connection.send(metadata)
            async for message in connection:
                try:
                    reply = await loop.run_in_executor(worker, answer, policy, message)
                except Exception as exc:  # noqa: BLE001 - this connection's error, sent to it; the server goes on
                    print(f"{connection.remote_address}: {error_text(exc).splitlines()[0]}", file=sys.stderr, flush=True)
                    await connection.send(error_text(exc))
                    await connection.close(1011, "error; its traceback is in the previous frame")
                    return
                await connection.send(reply)
        except ConnectionClosed:  # the client left, mid-request too
            return

    async with websocket_server(handle, sock=sock, max_size=MAX_FRAME, compression=None):
        host, port = sock.getsockname()[:2]
        if ready is not None:
            ready(f"ws://{host}:{port}")
        await stop.wait()
    worker.shutdown(wait=False, cancel_futures=True)


def bind(host: str, port: int) -> socket.socket:
    """A socket bound to (host, port), or SystemExit(2) with one line naming the port and the fix."""
    family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(address)
    except OSError as exc:
        sock.close()
        busy = "is in use (another server?); stop what holds it or" if exc.errno == errno.EADDRINUSE else \
            f"cannot be bound ({exc.strerror});"
        print(f"error: port {port} on {host} {busy} pass another --port (0 picks a free one)", file=sys.stderr)
        raise SystemExit(2) from None
    return sock


def load_policy_class(spec: str):
    """'module:Class' or 'path/to/file.py:Class' -> the class."""
    where, _, name = spec.rpartition(":")
    if not where or not name:
        raise SystemExit(f"error: --policy {spec!r}: give MODULE:CLASS or FILE.py:CLASS")
    if where.endswith(".py"):
        module_spec = importlib.util.spec_from_file_location(Path(where).stem, where)
        module = importlib.util.module_from_spec(module_spec)
        module_spec.loader.exec_module(module)
    else:
        module = importlib.import_module(where)
    return getattr(module, name)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="scripted_lift:BlindLiftExpert", help="MODULE:CLASS or FILE.py:CLASS")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on [127.0.0.1]")
    parser.add_argument("--port", type=int, default=8000, help="port (0: a free one, printed) [8000]")
    args = parser.parse_args(argv)
    sock = bind(args.host, args.port)  # before the policy loads: a busy port fails at once
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    policy = load_policy_class(args.policy)()
    name = (getattr(policy, "metadata", None) or {}).get("name", type(policy).__name__)

    def ready(url: str) -> None:
        print(f"serving {name} on {url}", flush=True)

    try:
        asyncio.run(serve(policy, sock, ready))
    finally:
        sock.close()
    print(f"stopped serving {name}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

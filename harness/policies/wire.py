"""openpi's websocket protocol on the wire: msgpack with numpy arrays, the JSON views of a server's metadata, and
the connection to a policy server (`ServerClient`) with the errors it raises.

A frame is one msgpack map. An ndarray travels as the map {b"__ndarray__": True, b"data": its C-order bytes,
b"dtype": dtype.str, b"shape": shape}, a numpy scalar as {b"__npgeneric__": True, b"data": item, b"dtype": str};
object, void and complex dtypes are refused both ways. This is openpi-client's `msgpack_numpy` format: `packb` and
`unpackb` use that module when openpi-client is installed (`CODEC` says which) and the same format written here
otherwise; tests/policies/test_served_client.py checks the two byte for byte.

`metadata_json` turns a server's metadata into JSON for the manifest (arrays summarised by dtype and shape),
`metadata_digest` into the identity of a server without a declared fingerprint (arrays hashed by their bytes).

`ServerClient` is written on websockets' sync client (openpi's own has no timeouts and no reconnection): the
connection opens on first use (CONNECT_TIMEOUT_S), every frame from the server is awaited at most its reply timeout
(REPLY_TIMEOUT_S by default), and any failure drops the connection so the next call opens a new one. A refused, lost
or silent server is `ServerLostError` (infrastructure: the episode is retried), a text frame or a malformed reply
`ServerError` (the episode fails), another policy behind the address on reconnection `ServerChangedError` (the run
stops). No proxy and no keep-alive pings: a server busy compiling answers late, not never. harness/policies/served.py
re-exports all of these.
"""

from __future__ import annotations

import hashlib
import json
import threading
from typing import Any

import msgpack
import numpy as np

from harness.policy import EnvMismatchError

REFUSED_KINDS = ("V", "O", "c")  # void, object, complex: no safe or portable byte form


def _pack(obj: Any) -> Any:
    """msgpack's `default` hook: an ndarray or numpy scalar -> its tagged map; anything else unchanged."""
    if isinstance(obj, (np.ndarray, np.generic)) and obj.dtype.kind in REFUSED_KINDS:
        raise ValueError(f"cannot send an array of dtype {obj.dtype} to a policy server (object, void and complex "
                         f"dtypes are refused)")
    if isinstance(obj, np.ndarray):
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    return obj


def _unpack(obj: dict) -> Any:
    """msgpack's `object_hook`: a tagged map -> its ndarray (read-only, over the frame's bytes) or numpy scalar."""
    if b"__ndarray__" in obj:
        dtype = _dtype(obj[b"dtype"])
        return np.ndarray(buffer=obj[b"data"], dtype=dtype, shape=tuple(obj[b"shape"]))
    if b"__npgeneric__" in obj:
        return _dtype(obj[b"dtype"]).type(obj[b"data"])
    return obj


def _dtype(text: Any) -> np.dtype:
    dtype = np.dtype(text)
    if dtype.kind in REFUSED_KINDS:
        raise ValueError(f"a policy server sent an array of dtype {dtype} (object, void and complex dtypes are "
                         f"refused)")
    return dtype


def own_packb(obj: Any) -> bytes:
    return msgpack.packb(obj, default=_pack)


def own_unpackb(data: bytes) -> Any:
    return msgpack.unpackb(data, object_hook=_unpack)


try:  # openpi-client's codec where installed (the optional extra `served`): the reference of the format
    from openpi_client import msgpack_numpy as _openpi

    packb, unpackb, CODEC = _openpi.packb, _openpi.unpackb, "openpi-client"
except ImportError:
    packb, unpackb, CODEC = own_packb, own_unpackb, "harness"


def _jsonable(value: Any, array) -> Any:
    """`value` as JSON data: bytes keys and values decoded, numpy scalars as items, ndarrays by `array(value)`."""
    if isinstance(value, np.ndarray):
        return array(value)
    if isinstance(value, np.generic):
        return value.item() if value.dtype.kind not in REFUSED_KINDS else str(value)
    if isinstance(value, dict):
        return {_key(k): _jsonable(v, array) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v, array) for v in value]
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace") if len(value) <= 256 else {"bytes": len(value),
                                                                            "sha256": hashlib.sha256(value).hexdigest()}
    if isinstance(value, float) and not np.isfinite(value):
        return repr(value)
    if value is None or isinstance(value, (str, int, float, bool)):
        return value
    return repr(value)


def _key(key: Any) -> str:
    return key.decode("utf-8", "replace") if isinstance(key, bytes) else str(key)


def array_digest(array: np.ndarray) -> dict:
    """{"dtype", "shape", "sha256"} of an array: its identity in a fingerprint."""
    array = np.ascontiguousarray(array)
    return {"dtype": array.dtype.str, "shape": list(array.shape), "sha256": hashlib.sha256(array.tobytes()).hexdigest()}


def metadata_json(metadata: Any) -> Any:
    """The metadata as JSON data for the manifest: every array replaced by {"dtype", "shape"}."""
    return _jsonable(metadata, lambda a: {"dtype": a.dtype.str, "shape": list(a.shape)})


def metadata_digest(metadata: Any) -> str:
    """sha256 (hex) of the canonical JSON of the metadata (sorted keys, no spaces), arrays by `array_digest`."""
    data = _jsonable(metadata, array_digest)
    return hashlib.sha256(json.dumps(data, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


CONNECT_TIMEOUT_S = 10.0  # seconds to open a connection (TCP and the websocket handshake)
REPLY_TIMEOUT_S = 60.0  # seconds to wait for any one frame from the server (metadata or reply)
MAX_FRAME_BYTES = 256 * 2**20  # the largest frame accepted from a server
SERVE_HINT = "start it (octo-harness serve --model PATH --port N) or fix --model"


class ServerLostError(RuntimeError):
    """The policy server refused, dropped or stopped answering the connection: an infrastructure failure
    (harness.run.executor.failure_of), retried on a new connection."""

    lost = "policy server"


class ServerTimeoutError(ServerLostError):
    """The policy server sent nothing within the reply timeout (the connection is dropped)."""


class ServerError(RuntimeError):
    """The policy server answered with an error (a text frame; `text` holds it whole) or a malformed frame: an
    episode failure. openpi's server closes after an error, so the next call connects again."""

    def __init__(self, message: str, text: str = ""):
        super().__init__(message)
        self.text = text


class ServerChangedError(EnvMismatchError):
    """A reconnection found another policy behind the address (its fingerprint changed): the run stops."""


def error_line(text: str) -> str:
    """The line of a server's error text that says what failed: a traceback's last line, else the first."""
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()] or ["(no text)"]
    return lines[-1] if lines[0].startswith("Traceback") else lines[0]

def server_identity(metadata: dict) -> str:
    """The identity a server declares (metadata "fingerprint"), else "metadata-sha256:<wire.metadata_digest>"."""
    declared = metadata.get("fingerprint")
    return declared if isinstance(declared, str) and declared else f"metadata-sha256:{metadata_digest(metadata)}"


# ---------------------------------------------------------------------------------------------- the connection

class ServerClient:
    """One websocket connection to a policy server, opened on first use and again after any failure; one call at a
    time (a lock). Picklable: a copy connects anew."""

    def __init__(self, address: str, timeout_s: float = REPLY_TIMEOUT_S, connect_timeout_s: float = CONNECT_TIMEOUT_S):
        self.address = address
        self.timeout_s = float(timeout_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self.identity: str | None = None  # the first connection's server_identity: a reconnection must find it again
        self._metadata: dict | None = None
        self._ws = None
        self._lock = threading.Lock()

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_ws": None, "_lock": None}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, _lock=threading.Lock())

    def metadata(self) -> dict:
        """The server's metadata (connecting when not connected)."""
        with self._lock:
            if self._ws is None:
                self._open()
            return self._metadata

    def call(self, payload: dict) -> dict:
        """Send one frame, return the server's reply (a map)."""
        data = packb(payload)
        with self._lock:
            if self._ws is None:
                self._open()
            from websockets.exceptions import ConnectionClosed

            try:
                self._ws.send(data)
            except (ConnectionClosed, OSError) as e:
                raise self._lost(e) from None
            except BaseException:
                self.drop()
                raise
            reply = self._receive("reply")
        if not isinstance(reply, dict):
            raise ServerError(f"the policy server sent a {type(reply).__name__}, not a map, as its reply")
        return reply

    def _lost(self, cause: BaseException) -> ServerLostError:
        """The connection dropped under a send or a receive: closed here, and the error to raise."""
        self.drop()
        return ServerLostError(f"the policy server at {self.address} dropped the connection ({_cause(cause)}); "
                               f"{SERVE_HINT}")

    def drop(self) -> None:
        """Close the connection (quietly); the next call opens a new one."""
        ws, self._ws = self._ws, None
        if ws is not None:
            try:
                ws.close()
            except Exception:
                pass

    close = drop

    def _open(self) -> None:
        try:
            from websockets.exceptions import InvalidHandshake, InvalidURI
            from websockets.sync.client import connect
        except ImportError:
            raise ImportError("--model ws:// needs the websocket client: pip install -e '.[served]'") from None
        try:
            self._ws = connect(self.address, open_timeout=self.connect_timeout_s, close_timeout=1.0,
                               max_size=MAX_FRAME_BYTES, compression=None, ping_interval=None, proxy=None)
        except InvalidURI as e:
            raise ValueError(f"--model {self.address}: not a websocket address ({e}); give ws://HOST:PORT") from None
        except (OSError, InvalidHandshake, TimeoutError) as e:
            raise ServerLostError(f"cannot reach the policy server at {self.address} ({_cause(e)}); "
                                  f"{SERVE_HINT}") from None
        metadata = self._receive("metadata")
        if not isinstance(metadata, dict):
            self.drop()
            raise ServerError(f"the policy server at {self.address} sent a {type(metadata).__name__}, not a map, as "
                              f"its metadata; is it an openpi policy server?")
        identity = server_identity(metadata)
        if self.identity is not None and identity != self.identity:
            self.drop()
            raise ServerChangedError(f"the policy server at {self.address} now serves another policy ({identity}, "
                                     f"was {self.identity}); restart the run against one policy")
        self.identity, self._metadata = identity, metadata

    def _receive(self, what: str):
        from websockets.exceptions import ConnectionClosed

        try:
            data = self._ws.recv(timeout=self.timeout_s)
        except TimeoutError:
            self.drop()
            raise ServerTimeoutError(f"the policy server at {self.address} sent no {what} within {self.timeout_s:g} s; "
                                     f"check that it is running and not stuck") from None
        except (ConnectionClosed, OSError) as e:
            raise self._lost(e) from None
        except BaseException:
            self.drop()
            raise
        if isinstance(data, str):
            self.drop()
            raise ServerError(f"the policy server failed: {error_line(data)}", data)
        try:
            return unpackb(data)
        except Exception as e:
            self.drop()
            raise ServerError(f"the policy server sent a frame that is not openpi's msgpack ({_cause(e)})") from None


def _cause(exc: BaseException) -> str:
    return (str(exc) or type(exc).__name__).splitlines()[0]

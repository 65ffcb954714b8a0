"""`octo-harness serve`: any `Policy` behind openpi's websocket protocol, so a harness run, openpi's own client or a
robot elsewhere can query it (the protocol: harness/policies/wire.py and served.py, the client side).

On connect the server sends its metadata (`metadata`: the policy's identity, conventions and sizes under
"octo_harness"); then each binary frame is answered by one reply. A frame holding "octo_harness/requests" carries up
to `max_batch` of the harness's own `InferenceRequest`s (observation window, instruction, goals, seed, step), which
are rebuilt and answered by the policy's stateless inference with a fixed `inference_batch`, so the chunks are
bit-identical to an in-process run of the same checkpoint and PolicyConfig. Any other frame is a plain openpi
observation (`plain_request`): one observation in the harness's key names, window-padded, seed 0. An error while
answering is sent as a text frame (its one-line summary, then the traceback) and closes that connection only, as
openpi's server does. Inference runs in one worker thread, one request at a time, so the event loop keeps serving
handshakes, pings and disconnects.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import errno
import hashlib
import json
import signal
import socket
import sys
import threading
import traceback
from pathlib import Path
from typing import Any, Callable

import numpy as np

from harness.conventions import CheckpointConventions
from harness.policies.base import Policy
from harness.policy import InferenceRequest, TaskPrompt, resize_frame, window_from_entries
from harness.policy_config import PolicyConfig

REQUESTS, RESULTS = "octo_harness/requests", "octo_harness/results"  # the extension's keys (docs/serving.md)
VERSION = 1  # of the "octo_harness" metadata block
MAX_FRAME = 64 * 2 ** 20  # bytes of one incoming frame; a larger one closes its connection (websockets: code 1009)
DEFAULT_MAX_BATCH = 8  # requests one extension frame may carry
# the PolicyConfig fields that change a served chunk; with the checkpoint's fingerprint, the served fingerprint
FINGERPRINT_FIELDS = ("dataset_key", "action_normalization", "proprio_normalization", "sampler", "inference_batch")


class FrameError(ValueError):
    """A frame this server cannot answer (message: one line naming what is wrong); closes its connection only."""


class BindError(ValueError):
    """The address cannot be bound: a busy port, a host that does not resolve (one line naming the fix; exit 2)."""


# ------------------------------------------------------------------------------------------------- identity


def served_fingerprint(model_fingerprint: str, fields: dict) -> str:
    """"sha256:<hex>" of the canonical JSON {"model": the checkpoint's fingerprint, "policy": `fields`} (the
    FINGERPRINT_FIELDS with the dataset key resolved): another checkpoint or config is another served policy."""
    data = {"model": model_fingerprint, "policy": {k: fields.get(k) for k in FINGERPRINT_FIELDS}}
    return "sha256:" + hashlib.sha256(json.dumps(data, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _lists(value: Any) -> Any:
    """Statistics as plain data: arrays as (nested) lists, numpy scalars as items."""
    if isinstance(value, dict):
        return {str(k): _lists(v) for k, v in value.items()}
    if isinstance(value, (np.ndarray, list, tuple)):
        return np.asarray(value).tolist()
    return value.item() if isinstance(value, np.generic) else value


def example_frames(policy: Policy) -> dict[str, np.ndarray]:
    """{camera key: (h, w, 3) uint8} the newest frame of each camera in the checkpoint's example batch ({} if none)."""
    observation = (policy.example_batch or {}).get("observation") or {}
    frames = {}
    for key in policy.image_sizes:
        if key in observation:
            frame = np.asarray(observation[key])
            frames[key] = np.ascontiguousarray(frame.reshape(-1, *frame.shape[-3:])[-1], dtype=np.uint8)
    return frames


def metadata(policy: Policy, infer, fingerprint: str, name: str, conventions: CheckpointConventions,
             max_batch: int) -> dict:
    """The frame a client receives on connect (docs/serving.md#the-metadata)."""
    key = infer.dataset_key
    statistics = policy.dataset_statistics.get(key) if key is not None else None
    return {"fingerprint": fingerprint, "name": name, "octo_harness": {
        "version": VERSION, "max_batch": int(max_batch), "window": int(policy.window_size),
        "image_sizes": {k: [int(h), int(w)] for k, (h, w) in policy.image_sizes.items()},
        "lowdim_sizes": {k: int(d) for k, d in policy.lowdim_sizes.items()},
        "goal_image_sizes": {k: [int(h), int(w)] for k, (h, w) in policy.goal_image_sizes.items()},
        "takes_language": bool(policy.takes_language), "action_horizon": int(policy.action_horizon),
        "action_dim": int(infer.action_dim), "dataset_key": key,
        "dataset_statistics": {key: _lists(statistics)} if statistics is not None else {},
        "image_convention": conventions.env.get("image_convention"), "action_space": conventions.env.get("action_space"),
        "example_frames": example_frames(policy), "conventions": declared(conventions, key)}}


def declared(conventions: CheckpointConventions, dataset_key: str | None) -> dict:
    """The checkpoint's harness.toml as a client's run reads it ([env], [policy]; the tokenizer stays here), with the
    dataset key the server unnormalises with."""
    data = conventions.to_dict()
    policy = {**data["policy"], **({"dataset_key": dataset_key} if dataset_key is not None else {})}
    return {"format": data["format"], "env": data["env"], "policy": policy}


# ------------------------------------------------------------------------------------------------- requests


def _array(value: Any, where: str, shape: tuple, kinds: str) -> np.ndarray:
    if not isinstance(value, np.ndarray):
        raise FrameError(f"{where}: expected an array of shape {shape}, got {type(value).__name__}")
    if value.shape != shape or value.dtype.kind not in kinds:
        raise FrameError(f"{where}: expected shape {shape} ({ {'u': 'uint8', 'b': 'bool'}.get(kinds, 'float')}), "
                         f"got {value.shape} {value.dtype}")
    return value


def _instruction(value: Any, where: str) -> str:
    if value is None:
        return ""
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if not isinstance(value, str):
        raise FrameError(f"{where}: expected a string, got {type(value).__name__}")
    return value


def _integer(value: Any, where: str) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise FrameError(f"{where}: expected an integer, got {value!r:.60}")
    return int(value)


def extension_request(item: Any, policy: Policy, index: int) -> InferenceRequest:
    """One entry of an extension frame -> the InferenceRequest it carries (shapes checked against the policy)."""
    where = f"{REQUESTS}[{index}]"
    if not isinstance(item, dict) or not isinstance(item.get("observation"), dict):
        raise FrameError(f"{where}: expected a map with an 'observation' map")
    given, window = item["observation"], int(policy.window_size)
    observation: dict = {}
    for key, (h, w) in policy.image_sizes.items():
        observation[key] = _array(given.get(key), f"{where}.observation.{key}", (window, h, w, 3), "u")
    for key, dims in policy.lowdim_sizes.items():
        observation[key] = _array(given.get(key), f"{where}.observation.{key}", (window, dims), "fiu").astype(np.float32)
    observation["timestep_pad_mask"] = _array(given.get("timestep_pad_mask"), f"{where}.observation.timestep_pad_mask",
                                              (window,), "b")
    masks = given.get("pad_mask_dict")
    if not isinstance(masks, dict):
        raise FrameError(f"{where}.observation.pad_mask_dict: expected a map of (window,) bool arrays")
    observation["pad_mask_dict"] = {k: _array(masks.get(k), f"{where}.observation.pad_mask_dict.{k}", (window,), "b")
                                    for k in [*policy.image_sizes, *policy.lowdim_sizes]}
    goals = item.get("goals")
    if goals is not None:
        if not isinstance(goals, dict):
            raise FrameError(f"{where}.goals: expected a map of (h, w, 3) uint8 images or nil")
        goals = {k: _array(goals.get(k), f"{where}.goals.{k}", (h, w, 3), "u")
                 for k, (h, w) in policy.goal_image_sizes.items()}
    return InferenceRequest(observation, TaskPrompt.of(_instruction(item.get("instruction"), f"{where}.instruction"),
                                                       goals),
                            _integer(item.get("seed"), f"{where}.seed"), _integer(item.get("step"), f"{where}.step"))


def plain_request(frame: dict, policy: Policy) -> InferenceRequest:
    """A plain openpi frame: ONE observation in the harness's key names (image_* (H, W, 3) uint8, resized to the
    policy's sizes; low-dim keys (dims,)), "prompt" or "instruction", an optional "step"; window-padded as the
    closed loop pads an episode's first step, seed 0."""
    entry = {}
    for key, size in policy.image_sizes.items():
        frame_ = frame.get(key)
        if not isinstance(frame_, np.ndarray) or frame_.ndim != 3 or frame_.shape[-1] != 3 or frame_.dtype != np.uint8:
            raise FrameError(f"{key}: the policy reads an (H, W, 3) uint8 image under this key "
                             f"(got {type(frame_).__name__ if not isinstance(frame_, np.ndarray) else frame_.shape}); "
                             f"send the keys {[*policy.image_sizes, *policy.lowdim_sizes]}")
        entry[key] = resize_frame(np.ascontiguousarray(frame_), size)
    for key, dims in policy.lowdim_sizes.items():
        value = frame.get(key)
        if not isinstance(value, np.ndarray) or value.shape != (dims,) or value.dtype.kind not in "fiu":
            raise FrameError(f"{key}: the policy reads a ({dims},) float array under this key")
        entry[key] = value.astype(np.float32)
    observation = window_from_entries([entry], int(policy.window_size), [*policy.image_sizes, *policy.lowdim_sizes])
    instruction = _instruction(frame.get("prompt", frame.get("instruction")), "prompt")
    step = _integer(frame.get("step", 0), "step")
    return InferenceRequest(observation, TaskPrompt.of(instruction), 0, step)


def warm_up_request(policy: Policy) -> InferenceRequest:
    """A request of the policy's shapes (zeros) that compiles its one batch shape before the server says it is ready."""
    entry = {k: np.zeros((h, w, 3), np.uint8) for k, (h, w) in policy.image_sizes.items()}
    entry.update({k: np.zeros(d, np.float32) for k, d in policy.lowdim_sizes.items()})
    goals = None if policy.takes_language else {k: np.zeros((h, w, 3), np.uint8)
                                                for k, (h, w) in policy.goal_image_sizes.items()}
    observation = window_from_entries([entry], int(policy.window_size), [*policy.image_sizes, *policy.lowdim_sizes])
    return InferenceRequest(observation, TaskPrompt.of("", goals or None), 0, 0)


# ------------------------------------------------------------------------------------------------- the server


def error_text(exc: BaseException) -> str:
    """The text frame of an error: its one-line summary, then the traceback (openpi's client raises with it)."""
    summary = " ".join(f"{type(exc).__name__}: {exc}".split())[:1000]
    return summary + "\n" + "".join(traceback.format_exception(exc))


def bind(host: str, port: int) -> socket.socket:
    """A socket bound to (host, port) (port 0: a free one), or BindError (one line naming the port and the fix)."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except socket.gaierror as exc:
        raise BindError(f"--host {host}: cannot resolve it ({exc.strerror}); give an address such as 127.0.0.1 "
                             "or 0.0.0.0") from None
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(address)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise BindError(f"port {port} on {host} is in use (another server?); stop what holds it or pass "
                                 "another --port (0 picks a free one)") from None
        raise BindError(f"cannot listen on {host}:{port}: {exc.strerror or exc}; pass another --port (0 picks a "
                             "free one) or --host") from None
    return sock


class PolicyServer:
    """One policy, one PolicyConfig, served: `metadata` on connect, `answer(frame)` per frame, `serve(sock)`."""

    def __init__(self, policy: Policy, config: PolicyConfig, model_fingerprint: str, *, name: str | None = None,
                 conventions: CheckpointConventions | None = None, max_batch: int = DEFAULT_MAX_BATCH,
                 warm_up: bool = True):
        if isinstance(max_batch, bool) or not isinstance(max_batch, int) or max_batch < 1:
            raise ValueError(f"--max-batch must be an integer >= 1, got {max_batch!r}")
        self.policy, self.config, self.max_batch = policy, config, max_batch
        self.infer = policy.inference(config)
        fields = {**{k: getattr(config, k) for k in FINGERPRINT_FIELDS}, "dataset_key": self.infer.dataset_key}
        self.fingerprint = served_fingerprint(model_fingerprint, fields)
        self.name = name or Path(str(policy.source).rstrip("/")).name
        self.metadata = metadata(policy, self.infer, self.fingerprint, self.name, conventions or CheckpointConventions(),
                                 max_batch)
        if warm_up:
            self.infer.warm_up(warm_up_request(policy))
        self._worker = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="policy-server")
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def answer(self, frame: Any) -> dict:
        """A decoded frame -> its reply: {RESULTS: [{"actions"}...]} for an extension frame, else {"actions"}."""
        if not isinstance(frame, dict):
            raise FrameError(f"a frame must be a map (an observation), got {type(frame).__name__}")
        if REQUESTS in frame:
            items = frame[REQUESTS]
            if not isinstance(items, (list, tuple)) or not 1 <= len(items) <= self.max_batch:
                raise FrameError(f"{REQUESTS}: expected a list of 1..{self.max_batch} requests (max_batch), got "
                                 f"{len(items) if isinstance(items, (list, tuple)) else type(items).__name__}")
            requests = [extension_request(item, self.policy, i) for i, item in enumerate(items)]
            return {RESULTS: [{"actions": np.asarray(r.chunk, np.float32)} for r in self.infer(requests)]}
        (result,) = self.infer([plain_request(frame, self.policy)])
        return {"actions": np.asarray(result.chunk, np.float32)}

    def _reply(self, message: bytes | str) -> bytes:
        from harness.policies.wire import own_unpackb, packb

        if isinstance(message, str):
            raise FrameError("text frames are not requests; send msgpack in a binary frame")
        try:
            frame = own_unpackb(message)  # strict: object, void and complex dtypes refused
        except Exception as exc:  # noqa: BLE001 - whatever msgpack or numpy say of bad bytes: that connection's error
            detail = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            raise FrameError(f"not a msgpack-numpy frame ({detail})") from None
        return packb(self.answer(frame))

    async def _handle(self, connection) -> None:
        from websockets.exceptions import ConnectionClosed

        from harness.policies.wire import packb

        loop = asyncio.get_running_loop()
        try:
            await connection.send(packb(self.metadata))
            async for message in connection:
                try:
                    reply = await loop.run_in_executor(self._worker, self._reply, message)
                except Exception as exc:  # noqa: BLE001 - this connection's error, sent to it; the server goes on
                    print(f"{connection.remote_address}: {error_text(exc).splitlines()[0]} (connection closed)",
                          file=sys.stderr, flush=True)
                    await connection.send(error_text(exc))
                    await connection.close(1011, "error; its traceback is in the previous frame")
                    return
                await connection.send(reply)
        except ConnectionClosed:  # the client left (mid-request too): its reply is dropped
            return

    @staticmethod
    def _health(connection, request):
        if request.path == "/healthz":
            return connection.respond(200, "OK\n")
        return None

    async def serve(self, sock: socket.socket, ready: Callable[[str], None] | None = None) -> None:
        """Serve on a bound socket until `stop()` (or SIGINT/SIGTERM when run in the main thread); `ready(url)` once
        it listens."""
        from websockets.asyncio.server import serve

        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._loop.add_signal_handler(signum, self._stop.set)
        async with serve(self._handle, sock=sock, max_size=MAX_FRAME, compression=None,
                         process_request=self._health):
            host, port = sock.getsockname()[:2]
            if ready is not None:
                ready(f"ws://{f'[{host}]' if ':' in host else host}:{port}")
            await self._stop.wait()
        self._worker.shutdown(wait=False, cancel_futures=True)

    def stop(self) -> None:
        """Stop serving (from any thread)."""
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)


# ------------------------------------------------------------------------------------------------- from a source


def checkpoint_conventions(source: str) -> CheckpointConventions:
    """The harness.toml conventions of a checkpoint source (a folder, random:<folder>, hf:// in the local cache)."""
    folder = None
    if source.startswith("hf://"):
        from harness.octo import checkpoint

        try:
            folder = checkpoint.resolve_checkpoint_dir(source)
        except Exception:  # noqa: BLE001 - not in the cache: loading reports it
            folder = None
    else:
        path = Path(source[len("random:"):] if source.startswith("random:") else source).expanduser()
        folder = path if path.is_dir() else None
    return CheckpointConventions.read(folder)


def server_for(source: str, overrides: dict | None = None, max_batch: int = DEFAULT_MAX_BATCH) -> PolicyServer:
    """The PolicyServer of `--model source`: its harness.toml's [policy] with `overrides` (None ignored) on top."""
    from harness.policies import family_of, load_policy, policy_fingerprint

    conventions = checkpoint_conventions(source)
    config = conventions.policy_config(overrides)
    options = {"text_tokenizer": conventions.text_tokenizer} if conventions.text_tokenizer else {}
    model_fp, _ = policy_fingerprint(source, **options)
    policy = load_policy(source, **options)
    return PolicyServer(policy, config, model_fp, name=family_of(source).run_label(source), conventions=conventions,
                        max_batch=max_batch)


def serve_until_stopped(server: PolicyServer, sock: socket.socket, label: str) -> None:
    """Serve on `sock` until SIGINT or SIGTERM: one line when ready (the real port when --port 0), one when stopped."""

    def ready(url: str) -> None:
        print(f"serving {label} (fingerprint {server.fingerprint}) on {url}", flush=True)

    try:
        asyncio.run(server.serve(sock, ready))
    finally:
        sock.close()
    print(f"stopped serving {label}", flush=True)

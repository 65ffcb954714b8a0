"""Policies behind an openpi-protocol websocket server (`--model ws://HOST:PORT`): the client side.

The wire (harness/policies/wire.py: the bytes, the connection and its errors): on connect the server sends one
msgpack frame, its metadata; then one reply per client frame. A server whose metadata has an "octo_harness" block
(`octo-harness serve`) takes the harness's own requests, up to its "max_batch" a frame ({"octo_harness/requests":
[InferenceRequest fields]} -> {"octo_harness/results": [{"actions"}]}), so its chunks are the in-process run's bit
for bit. Any other openpi server gets one observation dict per request, keyed by the conventions below, and answers
{"actions": (horizon, dim)}. A text frame is the server's error (`ServerError`, an episode failure); a refused,
lost or silent connection is `ServerLostError` (an infrastructure failure: `--retries` reruns the episode on a new
connection). openpi's own client has no timeouts, so this one is written on websockets' sync client:
CONNECT_TIMEOUT_S to connect, REPLY_TIMEOUT_S (or load's `timeout_s`) for every reply, and a new connection on the
next call after any failure.

The policy's identity is the server's: its metadata's "fingerprint", else "metadata-sha256:<digest of the
metadata>", with the content of the client's conventions file folded in (a different key mapping is another
protocol). The address never enters it: a restarted server on another port resumes the same run.

The conventions file (`--served-conventions FILE`, harness.toml format, whose [env] table may state the image
convention and action space too) describes a third-party server in its `[served]` table; every key optional, and
ignored for a server with the harness extension, whose metadata says all of it. `ServedPolicy.env_conventions`
holds the image convention and action space the metadata or [served] states:

    [served]
    window = 1                    # observations a request carries (> 1: each key sends the (window, ...) stack)
    action_horizon = 10           # actions per chunk (default: learnt from the first chunk)
    action_dim = 7                # dims of each action (default: learnt from the first chunk)
    dataset_key = "libero"        # recorded as the run's unnormalisation key (the server unnormalises)
    image_convention = "rot180"   # as [env] image_convention (give it in one of the two)
    action_space = "libero"       # as [env] action_space
    prompt = "prompt"             # the key the instruction goes in; "" sends none (the policy takes no language)

    [served.images]               # server key = [harness observation key, height, width] (replaces the default)
    "observation/image" = ["image_primary", 224, 224]
    "observation/wrist_image" = ["image_wrist", 224, 224]

    [served.state]                # server key = harness low-dim key ("proprio": 8-D) or [key, dims]
    "observation/state" = "proprio"

Without the file: "observation/image" <- image_primary at 224x224, "observation/state" <- proprio (8-D),
"prompt" <- the instruction, window 1 (openpi's LIBERO example keys, less its wrist camera: add it in the file).
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np

from harness.policies.base import Capabilities, Policy, PolicyFamily
from harness.policies.wire import (CONNECT_TIMEOUT_S, REPLY_TIMEOUT_S, ServerChangedError, ServerClient, ServerError,
                                   ServerLostError, ServerTimeoutError, metadata_json, server_identity)
from harness.policy import InferenceRequest, InferenceResult, resize_frame
from harness.policy_config import PolicyConfig

__all__ = ["CONNECT_TIMEOUT_S", "REPLY_TIMEOUT_S", "ServedConventions", "ServedFamily", "ServedPolicy", "declared_conventions",
           "ServerChangedError", "ServerClient", "ServerError", "ServerLostError", "ServerTimeoutError", "UnreachableServerError",
           "WebsocketInference"]

SERVED_SOURCE = "ws://"  # what the protocol records of any served source: the address is not the policy
EXTENSION, EXTENSION_VERSION = "octo_harness", 1
REQUESTS, RESULTS = "octo_harness/requests", "octo_harness/results"
NO_ADDRESS = "this run's policy was served; give its server's address with --model ws://HOST:PORT"
DEFAULT_IMAGES = {"observation/image": ("image_primary", 224, 224)}
DEFAULT_STATE = {"observation/state": ("proprio", 8)}
# what a server may declare, at most: bounds on what the client allocates per request from another process's word
LIMITS = {"max_batch": 256, "window": 64, "action_horizon": 1024, "action_dim": 64, "image_side": 4096, "lowdim": 4096}
KNOWN_STATE = {"proprio": 8}  # low-dim keys the envs give, by dims (harness.policy.ENV_LOWDIM_HELP)


def server_address(source: str) -> str:
    """`source` when it names a host (ws://HOST[:PORT][/path]); ValueError (one line) for the bare "ws://"."""
    if not urlsplit(source).hostname:
        raise ValueError(NO_ADDRESS)
    return source


def served_fingerprint(metadata: dict, conventions: bytes = b"") -> str:
    """The model fingerprint: the server's identity, with the client's conventions file content folded in."""
    identity = server_identity(metadata)
    if not conventions:
        return identity
    digest = hashlib.sha256(identity.encode() + b"\0" + conventions).hexdigest()
    return f"served-sha256:{digest}"


# ---------------------------------------------------------------------------------------------- conventions file

@dataclass(frozen=True)
class ServedConventions:
    """A third-party server's conventions (the [served] table); the defaults are openpi's LIBERO example's keys."""

    window: int = 1
    action_horizon: int | None = None
    action_dim: int | None = None
    dataset_key: str | None = None
    image_convention: str | None = None
    action_space: str | None = None
    prompt: str = "prompt"
    images: dict = field(default_factory=lambda: dict(DEFAULT_IMAGES))  # server key -> (obs key, height, width)
    state: dict = field(default_factory=lambda: dict(DEFAULT_STATE))  # server key -> (low-dim obs key, dims)

    @classmethod
    def parse(cls, table: dict, where: str, env: dict | None = None) -> "ServedConventions":
        from envs.options import ACTION_SPACES, IMAGE_CONVENTIONS
        from harness.conventions import ConventionsError

        def fail(what: str):
            raise ConventionsError(f"{where}: [served] {what}; fix the file")

        if not isinstance(table, dict):
            fail("must be a table")
        unknown = sorted(set(table) - {f.name for f in cls.__dataclass_fields__.values()})
        if unknown:
            fail(f"key(s) {unknown} unknown; allowed: {sorted(cls.__dataclass_fields__)}")
        values: dict = {}
        for key in ("window", "action_horizon", "action_dim"):
            if key in table:
                if not _positive(table[key]):
                    fail(f"{key} must be a positive integer, not {table[key]!r}")
                values[key] = table[key]
        for key, choices in (("dataset_key", None), ("prompt", None), ("image_convention", IMAGE_CONVENTIONS),
                             ("action_space", ACTION_SPACES)):
            if key in table:
                if not isinstance(table[key], str) or (choices and table[key] not in choices):
                    fail(f"{key} must be {' | '.join(choices) if choices else 'a string'}, not {table[key]!r}")
                if key in (env or {}) and (env or {})[key] != table[key]:
                    fail(f"{key} {table[key]!r} contradicts [env] {key} {env[key]!r}; give it once")
                values[key] = table[key]
        if "images" in table:
            images = table["images"]
            if not isinstance(images, dict) or not all(
                    isinstance(v, list) and len(v) == 3 and isinstance(v[0], str) and v[0].startswith("image_")
                    and _positive(v[1]) and _positive(v[2]) for v in images.values()):
                fail("images: each server key takes [\"image_<name>\", height, width]")
            values["images"] = {k: (v[0], int(v[1]), int(v[2])) for k, v in images.items()}
        if "state" in table:
            state = table["state"]
            parsed = {}
            for key, value in (state.items() if isinstance(state, dict) else [("", None)]):
                if isinstance(value, str) and value in KNOWN_STATE:
                    parsed[key] = (value, KNOWN_STATE[value])
                elif isinstance(value, list) and len(value) == 2 and isinstance(value[0], str) and _positive(value[1]):
                    parsed[key] = (value[0], int(value[1]))
                else:
                    fail(f"state: each server key takes \"proprio\" or [\"<low-dim key>\", dims], not {value!r}")
            values["state"] = parsed
        conventions = cls(**values)
        sizes: dict = {}
        for key, height, width in conventions.images.values():
            if sizes.setdefault(key, (height, width)) != (height, width):
                fail(f"images: {key} is given at two sizes")
        return conventions

    @classmethod
    def read(cls, path: str | Path | None) -> tuple["ServedConventions", bytes]:
        """(conventions, the file's bytes) of a conventions file; the defaults and b"" for None."""
        if path is None:
            return cls(), b""
        import tomllib

        from harness.bounded import MAX_TOML_BYTES, loads_toml, read_bytes
        from harness.conventions import ConventionsError

        if not Path(path).is_file():
            raise ConventionsError(f"{path}: no such conventions file; fix --served-conventions")
        content = read_bytes(path, MAX_TOML_BYTES, "TOML file")
        try:
            data = loads_toml(content.decode(), str(path))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ConventionsError(f"{path}: not valid TOML ({e}); fix the file") from None
        env = data.get("env") if isinstance(data.get("env"), dict) else {}
        return cls.parse(data.get("served", {}), str(path), env), content


def _positive(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value > 0


def _int(value):
    """A numpy or Python integer as int; anything else unchanged (for `_positive` to refuse)."""
    return int(value) if isinstance(value, (int, np.integer)) and not isinstance(value, bool) else value


# ---------------------------------------------------------------------------------------------- the policy

class ServedPolicy(Policy):
    """A policy behind a server, as a Policy: its conventions from the metadata's "octo_harness" block, else from
    the conventions file (ServedConventions); actions only (no attention, interventions or probes)."""

    preflight_from_chunk = True

    def __init__(self, source: str, client: ServerClient, metadata: dict,
                 conventions: ServedConventions | None = None, conventions_bytes: bytes = b""):
        self.source = source
        self.client = client
        self.metadata = metadata
        self.name = str(metadata.get("name") or "")
        self.server_fingerprint = server_identity(metadata)
        self.fingerprint = served_fingerprint(metadata, conventions_bytes)
        self.conventions = conventions or ServedConventions()
        block = metadata.get(EXTENSION)
        self.extension = parse_extension(block) if block is not None else None
        if self.extension is not None:
            ext = self.extension
            self.max_batch = ext["max_batch"]
            self.window_size = ext["window"]
            self.image_sizes = ext["image_sizes"]
            self.lowdim_sizes = ext["lowdim_sizes"]
            self.goal_image_sizes = ext["goal_image_sizes"]
            self.takes_language = ext["takes_language"]
            self.action_horizon, self.action_dim = ext["action_horizon"], ext["action_dim"]
            self.dataset_key = ext["dataset_key"]
            self.dataset_statistics = ext["dataset_statistics"]
            frames = ext["example_frames"]
            self.example_batch = {"observation": {k: np.asarray(v)[None, None] for k, v in frames.items()}} \
                if frames else None
            self.env_conventions = {k: ext[k] for k in ("image_convention", "action_space") if ext[k] is not None}
        else:
            conv = self.conventions
            self.max_batch = 1
            self.window_size = conv.window
            self.image_sizes = {key: (h, w) for key, h, w in conv.images.values()}
            self.lowdim_sizes = {key: dims for key, dims in conv.state.values()}
            self.goal_image_sizes = {}
            self.takes_language = bool(conv.prompt)
            self.action_horizon = conv.action_horizon or 1  # 1 (safe for either execution) until a chunk is seen
            self.action_dim = conv.action_dim
            self.dataset_key = conv.dataset_key
            self.dataset_statistics = {}
            self.example_batch = None
            self.env_conventions = {k: getattr(conv, k) for k in ("image_convention", "action_space")
                                    if getattr(conv, k) is not None}
        self.horizon_known = self.extension is not None or self.conventions.action_horizon is not None
        self.capabilities = Capabilities(attention=False, interventions=False, probes=False,
                                         batched=self.max_batch > 1)

    def inference(self, config: PolicyConfig) -> "WebsocketInference":
        return WebsocketInference(self, config)

    def describe(self) -> dict:
        return {"server": {"name": self.name, "fingerprint": self.server_fingerprint,
                           "extension": self.extension is not None}}

    def close(self) -> None:
        self.client.close()

    def learn(self, chunk: np.ndarray) -> None:
        """Take the horizon and dims of the first chunk where nothing declared them; ServerError on a chunk of
        other dims than declared or seen."""
        if self.action_dim is None:
            self.action_dim = int(chunk.shape[1])
        elif chunk.shape[1] != self.action_dim:
            raise ServerError(f"the policy server returned {chunk.shape[1]}-D actions; it declared or gave "
                              f"{self.action_dim}-D before")
        if not self.horizon_known:
            self.action_horizon, self.horizon_known = int(chunk.shape[0]), True


def parse_extension(block) -> dict:
    """The metadata's "octo_harness" block, checked (one-line ServerError naming the first bad field)."""
    def bad(what: str):
        raise ServerError(f"the policy server's metadata {EXTENSION!r} block has {what}; update the server or client")

    if not isinstance(block, dict):
        bad("no map")
    if block.get("version") != EXTENSION_VERSION:
        bad(f"version {block.get('version')!r} (this client reads {EXTENSION_VERSION})")
    out = {}
    for key in ("max_batch", "window", "action_horizon", "action_dim"):
        if not _positive(block.get(key)):
            bad(f"{key} {block.get(key)!r}, not a positive integer")
        if block[key] > LIMITS[key]:
            bad(f"{key} {block[key]}, more than this client takes ({LIMITS[key]})")
        out[key] = block[key]
    for key in ("image_sizes", "goal_image_sizes"):
        sizes = block.get(key) or {}
        if not isinstance(sizes, dict) or not all(isinstance(v, (list, tuple)) and len(v) == 2
                                                  and all(_positive(_int(x)) for x in v) for v in sizes.values()):
            bad(f"{key} {sizes!r}, not {{key: [height, width]}}")
        if any(int(x) > LIMITS["image_side"] for v in sizes.values() for x in v):
            bad(f"{key} {sizes!r}, a side over {LIMITS['image_side']} pixels")
        out[key] = {str(k): (int(v[0]), int(v[1])) for k, v in sizes.items()}
    lowdim = block.get("lowdim_sizes") or {}
    if not isinstance(lowdim, dict) or not all(_positive(_int(v)) for v in lowdim.values()):
        bad(f"lowdim_sizes {lowdim!r}, not {{key: dims}}")
    if any(int(v) > LIMITS["lowdim"] for v in lowdim.values()):
        bad(f"lowdim_sizes {lowdim!r}, a key over {LIMITS['lowdim']} dims")
    out["lowdim_sizes"] = {str(k): int(v) for k, v in lowdim.items()}
    out["takes_language"] = bool(block.get("takes_language", True))
    for key in ("dataset_key", "image_convention", "action_space"):
        value = block.get(key)
        if value is not None and not isinstance(value, str):
            bad(f"{key} {value!r}, not a string or nil")
        out[key] = value
    for key in ("dataset_statistics", "example_frames"):
        value = block.get(key) or {}
        if not isinstance(value, dict):
            bad(f"{key} that is not a map")
        out[key] = value
    return out


class WebsocketInference:
    """The served policy's stateless inference: `__call__(requests) -> results`, through the harness extension
    (up to `batch_size` requests a frame) or one openpi frame per request. Results carry chunks only."""

    def __init__(self, policy: ServedPolicy, config: PolicyConfig):
        self.policy = policy
        self.config = config
        self.client = policy.client
        self.batch_size = policy.max_batch
        self.dataset_key = policy.dataset_key
        self.action_dim = policy.action_dim
        self.probes: list = []

    def probe(self, name: str):
        raise KeyError(f"probe {name!r} is not on: a policy behind a server runs no probes")

    def warm_up(self, request: InferenceRequest) -> None:
        """One inference (the server compiles, the connection opens, the horizon and dims are learnt)."""
        self([request])

    def __call__(self, requests: list[InferenceRequest]) -> list[InferenceResult]:
        out: list[InferenceResult] = []
        for i in range(0, len(requests), self.batch_size):
            group = requests[i:i + self.batch_size]
            if self.policy.extension is not None:
                start = time.perf_counter()
                chunks = self._extension_call(group)
                seconds = time.perf_counter() - start
                out.extend(self._result(chunk, seconds) for chunk in chunks)
            else:
                for request in group:
                    start = time.perf_counter()
                    chunk = self._chunk(self.client.call(self.openpi_frame(request)))
                    out.append(self._result(chunk, time.perf_counter() - start))
        return out

    def _result(self, chunk: np.ndarray, seconds: float) -> InferenceResult:
        self.policy.learn(chunk)
        self.action_dim = self.policy.action_dim
        return InferenceResult(chunk, None, None, seconds, None)

    def _extension_call(self, requests: list[InferenceRequest]) -> list[np.ndarray]:
        payload = {REQUESTS: [{"observation": r.observation, "instruction": r.task.instruction, "goals": r.task.goals,
                               "seed": int(r.seed), "step": int(r.step)} for r in requests]}
        reply = self.client.call(payload)
        results = reply.get(RESULTS)
        if not isinstance(results, list) or len(results) != len(requests):
            raise ServerError(f"the policy server's reply has no {RESULTS!r} list of {len(requests)} result(s)")
        return [self._chunk(result) for result in results]

    def openpi_frame(self, request: InferenceRequest) -> dict:
        """The openpi observation of a request: each mapped camera's newest frame at its size (h, w, 3) uint8,
        each low-dim key's (dims,) float32 (a window > 1: the (window, ...) stacks), the instruction."""
        conv, observation = self.policy.conventions, request.observation
        newest = self.policy.window_size == 1
        frame: dict = {}
        for server_key, (key, height, width) in conv.images.items():
            images = [resize_frame(np.asarray(f), (height, width)) for f in observation[key]]
            frame[server_key] = images[-1] if newest else np.stack(images)
        for server_key, (key, _) in conv.state.items():
            values = np.asarray(observation[key], np.float32)
            frame[server_key] = values[-1] if newest else values
        if conv.prompt:
            frame[conv.prompt] = request.task.instruction
        return frame

    @staticmethod
    def _chunk(result) -> np.ndarray:
        """(horizon, action_dim) float32 of a reply's "actions" (a 1-D one is horizon 1)."""
        actions = result.get("actions") if isinstance(result, dict) else None
        if not isinstance(actions, np.ndarray) or actions.ndim not in (1, 2) or actions.dtype.kind not in "fiu" \
                or actions.size == 0:
            raise ServerError(f"the policy server's reply has no \"actions\" array of (horizon, action_dim) "
                              f"(got {metadata_json(actions)!r:.120})")
        return np.array(actions if actions.ndim == 2 else actions[None], dtype=np.float32)


# ---------------------------------------------------------------------------------------------- the family

class UnreachableServerError(ValueError):
    """The policy server could not be reached, or sent no valid metadata, before anything ran: bad input (one line,
    exit 2). During an episode the same loss is a ServerLostError (an infrastructure failure)."""


def _metadata(address: str, timeout_s: float = REPLY_TIMEOUT_S) -> tuple[ServerClient, dict]:
    """(an open client, the server's metadata) of `address`, or UnreachableServerError (one line)."""
    client = ServerClient(address, timeout_s)
    try:
        return client, client.metadata()
    except (ServerLostError, ServerError) as exc:
        client.close()
        raise UnreachableServerError(str(exc).splitlines()[0]) from None


class ServedFamily(PolicyFamily):
    name = "served"
    description = "a policy behind an openpi-protocol websocket server (ws://HOST:PORT)"

    def accepts(self, source: str) -> bool:
        return source.startswith(("ws://", "wss://"))

    takes_served_conventions = True

    def declared_conventions(self, source: str) -> dict:
        return declared_conventions(source)

    def protocol_source(self, source: str) -> str:
        return SERVED_SOURCE

    def run_label(self, source: str) -> str:
        return "served"

    def fingerprint(self, source: str, text_tokenizer=None, served_conventions=None, **_) -> tuple[str, dict]:
        """(fingerprint, {"kind": "served", "name", "metadata": JSON summary}) of the server's policy (one
        connection, closed again)."""
        address = server_address(source)
        _, content = ServedConventions.read(served_conventions)
        client, metadata = _metadata(address)
        client.close()
        details = {"kind": "served", "name": str(metadata.get("name") or ""), "metadata": metadata_json(metadata)}
        return served_fingerprint(metadata, content), details

    def load(self, source: str, served_conventions=None, timeout_s: float = REPLY_TIMEOUT_S, **_) -> ServedPolicy:
        address = server_address(source)
        conventions, content = ServedConventions.read(served_conventions)
        client, metadata = _metadata(address, timeout_s)
        try:
            return ServedPolicy(source, client, metadata, conventions, content)
        except ServerError as exc:  # metadata it cannot use (a bad extension block)
            client.close()
            raise UnreachableServerError(str(exc).splitlines()[0]) from None


def declared_conventions(source: str) -> dict:
    """The harness.toml-format conventions the server at `source` declares ({} when none): its extension block's
    "conventions" (what `octo-harness serve` sends: the checkpoint's harness.toml, [env] and [policy]), else an
    [env] table of the image convention and action space it states. One connection, closed again."""
    client, metadata = _metadata(server_address(source))
    client.close()
    block = metadata.get(EXTENSION)
    if not isinstance(block, dict):
        return {}
    declared = block.get("conventions")
    if isinstance(declared, dict):
        return {k: v for k, v in declared.items() if k in ("format", "env", "policy")}
    env = {k: block[k] for k in ("image_convention", "action_space") if isinstance(block.get(k), str)}
    return {"env": env} if env else {}

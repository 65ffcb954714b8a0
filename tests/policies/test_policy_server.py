"""The policy server (harness/policies/server.py, `octo-harness serve`) and the standalone example server
(examples/serve/standalone_server.py), each started as a process on 127.0.0.1 and spoken to with a raw websockets
client and the wire codec: the metadata and its fingerprint, the harness extension's chunks bit-identical to the
in-process inference of the same checkpoint, a plain openpi frame, an error closing only its connection, a busy port,
SIGTERM; the scripted Lift expert's replies deterministic."""

from __future__ import annotations

import importlib
import queue
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import websockets  # noqa: E402,F401  (the served extra: scripts/_bootstrap.sh installs it; missing is a failure, not a skip)

import msgpack  # noqa: E402
from websockets.exceptions import ConnectionClosed  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from harness.policies.wire import packb, unpackb  # noqa: E402
from tests.helpers import REFERENCE_MODEL, REPO  # noqa: E402

MODEL = str(REFERENCE_MODEL)
START_TIMEOUT_S = 180  # import, load and compile on 2 busy cores (the compilation cache makes it ~10 s)


class Server:
    """A server process, its URL from the ready line, its output lines."""

    def __init__(self, argv: list[str]):
        self.process = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: queue.Queue = queue.Queue()
        self.stderr: list[str] = []
        threading.Thread(target=self._read, args=(self.process.stdout, self.lines.put), daemon=True).start()
        threading.Thread(target=self._read, args=(self.process.stderr, self.stderr.append), daemon=True).start()
        self.ready, self.url = "", ""

    @staticmethod
    def _read(stream, put) -> None:
        for line in stream:
            put(line.rstrip("\n"))

    def wait_ready(self) -> "Server":
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.5)
            except queue.Empty:
                if self.process.poll() is not None:
                    break
                continue
            if line.startswith("serving "):
                self.ready, self.url = line, line.rsplit(" on ", 1)[1]
                return self
        self.stop()
        raise AssertionError(f"no ready line; exit {self.process.poll()}; stderr: {self.stderr[-5:]}")

    def stop(self, signum: int = signal.SIGTERM) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signum)
        try:
            return self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            return self.process.wait()


def serve(*flags: str) -> Server:
    return Server([sys.executable, "-m", "harness.cli", "serve", "--model", MODEL, "--port", "0", *flags])


def fingerprint_of(server: Server) -> str:
    return server.ready.split("(fingerprint ", 1)[1].split(")", 1)[0]


def request(url: str, frame: dict):
    """(metadata, reply) of one frame on a new connection."""
    with connect(url, compression=None, max_size=None, open_timeout=30) as ws:
        metadata = unpackb(ws.recv(timeout=30))
        ws.send(packb(frame))
        return metadata, ws.recv(timeout=120)


@pytest.fixture(scope="module")
def servers():
    """The checkpoint served as its harness.toml says, and with another inference batch (the dataset key named as the
    checkpoint resolves it), started together."""
    started = [serve(), serve("--dataset-key", "robosuite_reference", "--inference-batch", "2", "--max-batch", "3")]
    try:
        yield [s.wait_ready() for s in started]
    finally:
        for s in started:
            s.stop()


@pytest.fixture(scope="module")
def server(servers):
    return servers[0]


@pytest.fixture(scope="module")
def policy():
    from harness.conventions import CheckpointConventions
    from harness.policies import load_policy

    loaded = load_policy(MODEL)
    return loaded, loaded.inference(CheckpointConventions.read(MODEL).policy_config())


def inference_requests(policy, n: int) -> list:
    from harness.policy import InferenceRequest, TaskPrompt, window_from_entries

    rng = np.random.default_rng(7)
    out = []
    for i in range(n):
        entry = {k: rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for k, (h, w) in policy.image_sizes.items()}
        entry.update({k: rng.normal(size=d).astype(np.float32) for k, d in policy.lowdim_sizes.items()})
        observation = window_from_entries([entry], policy.window_size, [*policy.image_sizes, *policy.lowdim_sizes])
        out.append(InferenceRequest(observation, TaskPrompt.of(["lift the cube", "pick up the red cube"][i % 2]),
                                    seed=11 + i, step=3 * i))
    return out


def wire_request(r) -> dict:
    return {"observation": r.observation, "instruction": r.task.instruction, "goals": r.task.goals, "seed": r.seed,
            "step": r.step}


def test_metadata_declares_the_checkpoint(server, policy):
    loaded, infer = policy
    with connect(server.url, compression=None) as ws:
        metadata = unpackb(ws.recv(timeout=30))
    block = metadata["octo_harness"]
    assert metadata["name"] == "octo-reference-robosuite"
    assert metadata["fingerprint"] == fingerprint_of(server)
    assert {k: block[k] for k in ("version", "max_batch", "window", "image_sizes", "lowdim_sizes", "goal_image_sizes",
                                  "takes_language", "action_horizon", "action_dim", "dataset_key", "image_convention",
                                  "action_space")} == {
        "version": 1, "max_batch": 8, "window": 1, "image_sizes": {"image_primary": [128, 128], "image_wrist": [64, 64]},
        "lowdim_sizes": {"proprio": 8}, "goal_image_sizes": {}, "takes_language": True, "action_horizon": 4,
        "action_dim": 7, "dataset_key": "robosuite_reference", "image_convention": "upright", "action_space": "robosuite"}
    assert block["conventions"] == {"format": "octo-harness-conventions/1", "env": {
        "action_space": "robosuite", "image_convention": "upright"}, "policy": {
        "dataset_key": "robosuite_reference", "action_normalization": "normal", "proprio_normalization": "normal"}}
    stats = loaded.dataset_statistics["robosuite_reference"]
    assert block["dataset_statistics"]["robosuite_reference"]["action"]["mean"] == np.asarray(stats["action"]["mean"]).tolist()
    for key, frame in block["example_frames"].items():
        assert np.array_equal(frame, np.asarray(loaded.example_batch["observation"][key])[0, -1]), key
    assert set(block["example_frames"]) == {"image_primary", "image_wrist"}
    assert server.ready == f"serving {MODEL} (fingerprint {metadata['fingerprint']}) on {server.url}"


def test_the_fingerprint_is_stable_and_follows_the_config(servers):
    """Each start's fingerprint is the one recomputed here from the checkpoint's files and the config (so every start
    of the same checkpoint and config gives it); another inference batch is another policy, the dataset key named as
    the checkpoint resolves it is not, and every inference field enters the hash. SIGTERM stops a server cleanly."""
    from harness.policies.fingerprint import model_fingerprint
    from harness.policies.server import served_fingerprint

    default, batched = servers
    fields = {"dataset_key": "robosuite_reference", "action_normalization": "normal",
              "proprio_normalization": "normal", "sampler": "latest", "inference_batch": 1}
    model = model_fingerprint(MODEL)[0]
    assert fingerprint_of(default) == served_fingerprint(model, fields)
    assert fingerprint_of(batched) == served_fingerprint(model, {**fields, "inference_batch": 2}) != fingerprint_of(default)
    metadata, reply = request(batched.url, {"octo_harness/requests": []})
    assert metadata["octo_harness"]["max_batch"] == 3 and "1..3" in reply
    assert batched.stop() == 0 and batched.lines.get(timeout=5).startswith("stopped serving")
    for key, value in (("dataset_key", "other"), ("action_normalization", "bounds"), ("sampler", "v0.1.0"),
                       ("proprio_normalization", "none"), ("inference_batch", 4)):
        assert served_fingerprint(model, {**fields, key: value}) != served_fingerprint(model, fields), key
    assert served_fingerprint("sha256:another", fields) != served_fingerprint(model, fields)


def test_extension_chunks_are_bit_identical_to_the_in_process_inference(server, policy):
    loaded, infer = policy
    requests = inference_requests(loaded, 3)
    _, reply = request(server.url, {"octo_harness/requests": [wire_request(r) for r in requests]})
    results = unpackb(reply)["octo_harness/results"]
    expected = infer(requests)
    assert len(results) == 3
    for got, want in zip(results, expected):
        assert got["actions"].dtype == np.float32 and got["actions"].shape == (4, 7)
        assert np.array_equal(got["actions"], want.chunk)


def test_a_plain_openpi_frame_is_one_observation(server, policy):
    """openpi's own client: one observation (images at any size, resized as the closed loop does), seed 0."""
    from harness.policy import InferenceRequest, TaskPrompt, resize_frame, window_from_entries

    client = importlib.import_module("openpi_client.websocket_client_policy")
    loaded, infer = policy
    rng = np.random.default_rng(3)
    frame = {"image_primary": rng.integers(0, 256, (256, 256, 3), dtype=np.uint8),
             "image_wrist": rng.integers(0, 256, (64, 64, 3), dtype=np.uint8),
             "proprio": rng.normal(size=8).astype(np.float32), "prompt": "lift the cube", "step": 5}
    actions = client.WebsocketClientPolicy(server.url).infer(frame)["actions"]
    entry = {k: resize_frame(frame[k], s) for k, s in loaded.image_sizes.items()} | {"proprio": frame["proprio"]}
    observation = window_from_entries([entry], 1, ["image_primary", "image_wrist", "proprio"])
    (want,) = infer([InferenceRequest(observation, TaskPrompt.of("lift the cube"), 0, 5)])
    assert np.array_equal(actions, want.chunk)


OBJECT_ARRAY = msgpack.packb({"proprio": {b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "|O", b"shape": [1]}})


@pytest.mark.parametrize("bad", [b"\xc1 not msgpack", OBJECT_ARRAY, "a text frame",
                                 {"octo_harness/requests": [{"observation": {"image_primary": np.zeros((1, 8, 8, 3),
                                                                                                        np.uint8)}}]}],
                         ids=["bytes", "object-array", "text", "wrong-shape"])
def test_an_error_is_a_text_frame_then_that_connection_closes(server, bad):
    with connect(server.url, compression=None, open_timeout=30) as ws:
        ws.recv(timeout=30)
        ws.send(packb(bad) if isinstance(bad, dict) else bad)
        text = ws.recv(timeout=60)
        assert isinstance(text, str) and "FrameError" in text.splitlines()[0] and "Traceback" in text
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=10)
    assert "octo_harness" in request(server.url, {"octo_harness/requests": []})[0]  # the server goes on


def test_a_client_leaving_mid_request_leaves_the_server_serving(server, policy):
    loaded, _ = policy
    ws = connect(server.url, compression=None, open_timeout=30)
    ws.recv(timeout=30)
    ws.send(packb({"octo_harness/requests": [wire_request(r) for r in inference_requests(loaded, 2)]}))
    ws.close()
    _, reply = request(server.url, {"octo_harness/requests": [wire_request(inference_requests(loaded, 1)[0])]})
    assert unpackb(reply)["octo_harness/results"][0]["actions"].shape == (4, 7)


def test_a_busy_port_is_one_line_and_exit_2():
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        done = subprocess.run([sys.executable, "-m", "harness.cli", "serve", "--model", MODEL, "--port", str(port)],
                              cwd=REPO, capture_output=True, text=True, timeout=120)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and f"port {port}" in lines[0] and "--port" in lines[0], done.stderr
    assert "loaded" not in done.stderr  # refused before the model loads


def test_the_standalone_server_serves_the_scripted_expert_deterministically():
    started = Server([sys.executable, str(REPO / "examples" / "serve" / "standalone_server.py"), "--port", "0"])
    try:
        started.wait_ready()
        state = np.array([-0.09, 0.0, 1.0, 3.1, 0.0, 1.5, 0.02, -0.02], np.float32)
        replies = [request(started.url, {"observation/state": state, "prompt": "lift the cube"}) for _ in range(2)]
        (metadata, first), (_, second) = replies
        assert metadata["name"] == "blind-scripted-lift" and metadata["action_horizon"] == 4
        assert metadata["fingerprint"].startswith("blind-scripted-lift/1:")
        first, second = unpackb(first)["actions"], unpackb(second)["actions"]
        assert first.shape == (4, 7) and first.dtype == np.float32 and np.array_equal(first, second)
        assert np.all(np.abs(first) <= 1.0) and first[0, 6] == -1.0  # away from the cube: gripper open, moving there
        _, error = request(started.url, {"nothing": 1})
        assert isinstance(error, str) and error.startswith("ValueError: no state")
    finally:
        assert started.stop() == 0

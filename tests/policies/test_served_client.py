"""The served-policy client (harness/policies/served.py, wire.py) against real websocket servers written here on
websockets' sync server, on 127.0.0.1: metadata and fingerprints, the harness extension's round trip, openpi's plain
key mapping, a server error, a silent server, a killed server, and the codec against openpi-client's."""

from __future__ import annotations

import importlib
import contextlib
import socket
import threading
import time

import numpy as np
import pytest

import websockets  # noqa: E402,F401  (the served extra: scripts/_bootstrap.sh installs it; missing is a failure, not a skip)

from websockets.sync.server import serve  # noqa: E402

from harness.policies import served  # noqa: E402
from harness.policies.served import (ServedConventions, ServedFamily, ServerChangedError, ServerError,  # noqa: E402
                                     ServerLostError, ServerTimeoutError)
from harness.policies.wire import own_packb, own_unpackb  # noqa: E402
from harness.policy import EnvMismatchError, InferenceRequest, TaskPrompt, resize_frame  # noqa: E402
from harness.policy_config import PolicyConfig  # noqa: E402

EXTENSION = {"version": 1, "max_batch": 2, "window": 2, "image_sizes": {"image_primary": [32, 40]},
             "lowdim_sizes": {"proprio": 8}, "goal_image_sizes": {}, "takes_language": True, "action_horizon": 4,
             "action_dim": 7, "dataset_key": "toy", "dataset_statistics": {"toy": {"action": {"mean": [0.0] * 7}}},
             "image_convention": "upright", "action_space": "robosuite",
             "example_frames": {"image_primary": np.full((32, 40, 3), 7, np.uint8)}}
HANG = object()  # an answer: never reply
DIE = object()  # an answer: drop the TCP connection without a close frame


def chunk_of(seed: int, step: int, horizon: int = 4, dim: int = 7) -> np.ndarray:
    return np.random.default_rng([seed, step]).standard_normal((horizon, dim)).astype(np.float32)


@contextlib.contextmanager
def policy_server(metadata: dict, answer):
    """ws://127.0.0.1:PORT of a server sending `metadata` (or what it returns per connection), then `answer(frame)`
    per frame: a dict (sent as msgpack), a str (a text frame, then close, as openpi's server), HANG or DIE. Frames
    received are in `.frames`."""
    stop = threading.Event()
    frames: list = []

    def handler(connection):
        connection.send(own_packb(metadata() if callable(metadata) else metadata))
        for message in connection:
            frame = own_unpackb(message)
            frames.append(frame)
            reply = answer(frame)
            if reply is HANG:
                stop.wait(10)
                return
            if reply is DIE:
                connection.socket.shutdown(socket.SHUT_RDWR)
                return
            if isinstance(reply, str):
                connection.send(reply)
                connection.close()
                return
            connection.send(own_packb(reply))

    with serve(handler, "127.0.0.1", 0, compression=None, max_size=None) as server:
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        server.frames = frames
        server.address = f"ws://127.0.0.1:{server.socket.getsockname()[1]}"
        try:
            yield server
        finally:
            stop.set()
            server.shutdown()
            thread.join(5)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def request(window: int = 1, seed: int = 3, step: int = 0, size=(32, 40), instruction="lift the can"):
    rng = np.random.default_rng(seed + step)
    pad = np.ones(window, bool)
    observation = {"image_primary": rng.integers(0, 256, (window, *size, 3), dtype=np.uint8),
                   "proprio": rng.standard_normal((window, 8)).astype(np.float32),
                   "timestep_pad_mask": pad, "pad_mask_dict": {"image_primary": pad, "proprio": pad}}
    return InferenceRequest(observation, TaskPrompt.of(instruction), seed, step)


def extension_answer(frame):
    items = frame["octo_harness/requests"]
    return {"octo_harness/results": [{"actions": chunk_of(r["seed"], r["step"])} for r in items]}


def test_fingerprint_is_the_servers_not_its_address(tmp_path):
    family = ServedFamily()
    with policy_server({"name": "toy", "extra": np.arange(3)}, extension_answer) as a, \
            policy_server({"name": "toy", "extra": np.arange(3)}, extension_answer) as b, \
            policy_server({"name": "toy", "extra": np.arange(4)}, extension_answer) as c:
        fp_a, details = family.fingerprint(a.address)
        fp_b, _ = family.fingerprint(b.address)
        fp_c, _ = family.fingerprint(c.address)
        assert fp_a == fp_b != fp_c and fp_a.startswith("metadata-sha256:")
        assert details == {"kind": "served", "name": "toy", "metadata": {"name": "toy",
                                                                          "extra": {"dtype": "<i8", "shape": [3]}}}
        assert a.address not in str(details) and family.protocol_source(a.address) == "ws://"
        conventions = tmp_path / "served.toml"
        conventions.write_text('[served]\nprompt = "task"\n')
        fp_conv, _ = family.fingerprint(a.address, served_conventions=str(conventions))
        conventions.write_text('[served]\nprompt = "instruction"\n')
        fp_conv2, _ = family.fingerprint(b.address, served_conventions=str(conventions))
        assert len({fp_a, fp_conv, fp_conv2}) == 3
    with policy_server({"fingerprint": "sha256:abc", "name": "x"}, extension_answer) as d:
        assert family.fingerprint(d.address)[0] == "sha256:abc"


def test_extension_round_trip_is_bit_identical():
    with policy_server({"fingerprint": "sha256:toy", "name": "toy", "octo_harness": EXTENSION}, extension_answer) as s:
        policy = ServedFamily().load(s.address)
        try:
            assert (policy.window_size, policy.action_horizon, policy.action_dim) == (2, 4, 7)
            assert policy.image_sizes == {"image_primary": (32, 40)} and policy.lowdim_sizes == {"proprio": 8}
            assert policy.capabilities.batched and not policy.capabilities.attention
            assert policy.example_batch["observation"]["image_primary"].shape == (1, 1, 32, 40, 3)
            assert policy.env_conventions == {"image_convention": "upright", "action_space": "robosuite"}
            assert policy.describe() == {"server": {"name": "toy", "fingerprint": "sha256:toy", "extension": True}}
            infer = policy.inference(PolicyConfig())
            assert (infer.batch_size, infer.dataset_key, infer.action_dim, infer.probes) == (2, "toy", 7, [])
            with pytest.raises(KeyError):
                infer.probe("attribution")
            requests = [request(window=2, seed=s_, step=t) for s_, t in ((1, 0), (2, 5), (3, 9))]
            results = infer(requests)
            assert len(s.frames) == 2  # max_batch 2: three requests in two frames
            for r, result in zip(requests, results):
                assert result.chunk.dtype == np.float32 and np.array_equal(result.chunk, chunk_of(r.seed, r.step))
                assert result.readout_attention is None and result.tokens is None and result.seconds >= 0
            sent = [item for frame in s.frames for item in frame["octo_harness/requests"]]
            for r, item in zip(requests, sent):
                assert (item["instruction"], item["seed"], item["step"], item["goals"]) == ("lift the can", r.seed,
                                                                                          r.step, None)
                for key in ("image_primary", "proprio", "timestep_pad_mask"):
                    got, want = item["observation"][key], r.observation[key]
                    assert got.dtype == want.dtype and np.array_equal(got, want)
                pad = item["observation"]["pad_mask_dict"]["proprio"]
                assert np.array_equal(pad, r.observation["timestep_pad_mask"])
        finally:
            policy.close()


def test_plain_openpi_server_gets_its_keys_and_the_horizon_is_learnt():
    with policy_server({}, lambda frame: {"actions": np.arange(14, dtype=np.float64).reshape(2, 7)}) as s:
        policy = ServedFamily().load(s.address)
        assert policy.extension is None and not policy.capabilities.batched and policy.preflight_from_chunk
        assert policy.image_sizes == {"image_primary": (224, 224)} and policy.lowdim_sizes == {"proprio": 8}
        assert (policy.window_size, policy.action_horizon, policy.action_dim) == (1, 1, None)
        assert policy.example_batch is None
        infer = policy.inference(PolicyConfig())
        r = request(window=1, size=(50, 60))
        (result,) = infer([r])
        frame = s.frames[0]
        assert sorted(frame) == ["observation/image", "observation/state", "prompt"]
        assert np.array_equal(frame["observation/image"], resize_frame(r.observation["image_primary"][-1], (224, 224)))
        assert frame["observation/state"].dtype == np.float32
        assert np.array_equal(frame["observation/state"], r.observation["proprio"][-1])
        assert frame["prompt"] == "lift the can"
        assert result.chunk.shape == (2, 7) and result.chunk.dtype == np.float32
        assert (policy.action_horizon, policy.action_dim, infer.action_dim) == (2, 7, 7)
        policy.close()


def test_conventions_file_maps_keys(tmp_path):
    path = tmp_path / "served.toml"
    path.write_text('[env]\naction_space = "libero"\n[served]\nwindow = 2\naction_horizon = 5\nprompt = "task"\n'
                    '[served.images]\n"cam/main" = ["image_primary", 16, 16]\n"cam/wrist" = ["image_wrist", 8, 8]\n'
                    '[served.state]\n"state" = ["joints", 3]\n')
    with policy_server({}, lambda frame: {"actions": np.zeros(7, np.float32)}) as s:
        policy = ServedFamily().load(s.address, served_conventions=str(path))
        assert policy.image_sizes == {"image_primary": (16, 16), "image_wrist": (8, 8)}
        assert (policy.window_size, policy.action_horizon, policy.lowdim_sizes) == (2, 5, {"joints": 3})
        pad = np.ones(2, bool)
        observation = {"image_primary": np.zeros((2, 16, 16, 3), np.uint8),
                       "image_wrist": np.ones((2, 8, 8, 3), np.uint8), "joints": np.zeros((2, 3), np.float32),
                       "timestep_pad_mask": pad, "pad_mask_dict": {}}
        (result,) = policy.inference(PolicyConfig())([InferenceRequest(observation, TaskPrompt.of("go"), 0, 0)])
        frame = s.frames[0]
        assert sorted(frame) == ["cam/main", "cam/wrist", "state", "task"]
        assert frame["cam/wrist"].shape == (2, 8, 8, 3) and frame["state"].shape == (2, 3)
        assert result.chunk.shape == (1, 7) and policy.action_horizon == 5  # declared: not overwritten
        policy.close()
    from harness.conventions import ConventionsError

    path.write_text('[env]\naction_space = "libero"\n[served]\naction_space = "robosuite"\n')
    with pytest.raises(ConventionsError, match="contradicts"):
        ServedConventions.read(path)
    path.write_text('[served.images]\n"x" = ["proprio", 16, 16]\n')
    with pytest.raises(ConventionsError, match="images"):
        ServedConventions.read(path)


def test_text_frame_is_a_server_error_then_the_next_call_reconnects():
    calls = []

    def answer(frame):
        calls.append(1)
        return "KeyError: 'observation/wrist_image'\nmore lines" if len(calls) == 1 else {"actions": np.ones((3, 7))}

    with policy_server({"name": "flaky"}, answer) as s:
        policy = ServedFamily().load(s.address)
        infer = policy.inference(PolicyConfig())
        with pytest.raises(ServerError, match="KeyError: 'observation/wrist_image'$") as error:
            infer([request()])
        assert "more lines" in error.value.text and not isinstance(error.value, ServerLostError)
        (result,) = infer([request()])
        assert result.chunk.shape == (3, 7)
        policy.close()


def test_another_policy_behind_the_address_stops_the_run():
    names = iter(["first", "second"])
    with policy_server(lambda: {"name": next(names)}, lambda frame: "RuntimeError: boom") as s:
        policy = ServedFamily().load(s.address)
        infer = policy.inference(PolicyConfig())
        with pytest.raises(ServerError, match="boom"):
            infer([request()])
        with pytest.raises(ServerChangedError, match="now serves another policy") as error:
            infer([request()])
        assert isinstance(error.value, EnvMismatchError)  # the executors stop the run on it
        policy.close()


def test_silent_server_times_out_in_bounded_time():
    with policy_server({}, lambda frame: HANG) as s:
        policy = ServedFamily().load(s.address, timeout_s=0.5)
        start = time.monotonic()
        with pytest.raises(ServerTimeoutError, match=f"{s.address} sent no reply within 0.5 s") as error:
            policy.inference(PolicyConfig())([request()])
        assert time.monotonic() - start < 5 and len(str(error.value).splitlines()) == 1
        assert isinstance(error.value, ServerLostError) and error.value.lost == "policy server"
        policy.close()


def test_killed_server_is_lost_and_an_infrastructure_failure():
    with policy_server({}, lambda frame: DIE) as s:
        policy = ServedFamily().load(s.address, timeout_s=5)
        with pytest.raises(ServerLostError, match=f"the policy server at {s.address} dropped the connection") as lost:
            policy.inference(PolicyConfig())([request()])
        policy.close()
    from harness.run.executor import failure_of

    assert failure_of(lost.value) == ("infrastructure", "policy server")
    assert failure_of(ServerTimeoutError("silent")) == ("infrastructure", "policy server")
    assert failure_of(ServerError("KeyError")) == ("episode", None)


def test_refused_and_missing_addresses_are_one_line():
    address = f"ws://127.0.0.1:{free_port()}"
    with pytest.raises(served.UnreachableServerError) as error:  # a ValueError: bad input, exit 2, before any episode
        ServedFamily().load(address)
    assert isinstance(error.value, ValueError) and not isinstance(error.value, ServerLostError)
    message = str(error.value)
    assert message.startswith(f"cannot reach the policy server at {address} (") and "\n" not in message
    assert message.endswith("; start it (octo-harness serve --model PATH --port N) or fix --model")
    for call in (ServedFamily().load, ServedFamily().fingerprint):
        with pytest.raises(ValueError, match="^this run's policy was served; give its server's address with "
                                             "--model ws://HOST:PORT$"):
            call("ws://")


@pytest.mark.parametrize("field, value", [("window", 10**6), ("max_batch", 10**9), ("action_dim", 10**5),
                                          ("image_sizes", {"image_primary": [10**6, 10**6]}),
                                          ("lowdim_sizes", {"proprio": 10**9}), ("version", 2)])
def test_a_hostile_or_foreign_metadata_block_is_one_line_before_anything_is_allocated(field, value):
    """A server declaring sizes that would make every request allocate gigabytes (or another extension version) is
    refused when the policy loads, in one line naming the field (exit 2 on the command line)."""
    with policy_server({"fingerprint": "big", "octo_harness": {**EXTENSION, field: value}}, extension_answer) as server:
        with pytest.raises(served.UnreachableServerError, match=field) as error:
            ServedFamily().load(server.address)
    assert "\n" not in str(error.value)


def test_own_codec_is_byte_compatible_with_openpi_client():
    msgpack_numpy = importlib.import_module("openpi_client.msgpack_numpy")
    payload = {"observation/image": np.arange(24, dtype=np.uint8).reshape(2, 4, 3), "s": np.float32(1.5),
               "mask": np.array([True, False]), "nested": [{"x": np.zeros((0, 3), ">f8")}], "prompt": "go", "n": None}
    assert own_packb(payload) == msgpack_numpy.packb(payload)
    for data in (own_packb(payload), msgpack_numpy.packb(payload)):
        a, b = own_unpackb(data), msgpack_numpy.unpackb(data)
        assert a["observation/image"].dtype == b["observation/image"].dtype == np.uint8
        assert np.array_equal(a["observation/image"], payload["observation/image"])
        assert a["s"] == b["s"] == np.float32(1.5)
        assert a["nested"][0]["x"].dtype.str == ">f8" and a["prompt"] == "go" and a["n"] is None
    with pytest.raises(ValueError):
        own_packb({"x": np.array([object()])})
    import msgpack

    complex_frame = msgpack.packb({"x": {b"__ndarray__": True, b"data": bytes(8), b"dtype": "<c8", b"shape": [1]}})
    with pytest.raises(ValueError, match="complex"):
        own_unpackb(complex_frame)
    assert served.REPLY_TIMEOUT_S == 60.0 and served.CONNECT_TIMEOUT_S > 0


def test_a_ray_replica_that_loses_its_server_reports_an_infrastructure_failure():
    """The policy replica (an async Ray actor; its class is plain Python) turns a lost server into an
    InfrastructureError that keeps its lost part across the pickling Ray does, so `--retries` reruns the episode."""
    import asyncio
    import pickle
    from concurrent.futures import ThreadPoolExecutor

    from harness.run.executor import InfrastructureError, failure_of
    from harness.run.ray_executor import PolicyReplica

    class LostServer:  # the replica's inference, as a served policy's when its server is gone
        batch_size = 1

        def __call__(self, requests):
            raise ServerLostError("the policy server at ws://127.0.0.1:1 dropped the connection (EOF)")

    replica = object.__new__(PolicyReplica)
    replica.inference, replica._pending, replica._running, replica.batches = LostServer(), [], False, []
    replica._thread, replica.progress = ThreadPoolExecutor(max_workers=1), {}

    async def one():
        return await replica.infer(request(), key=("Lift", 0))

    with pytest.raises(InfrastructureError) as error:
        asyncio.run(one())
    again = pickle.loads(pickle.dumps(error.value))
    assert again.lost == "policy server" and failure_of(again) == ("infrastructure", "policy server")

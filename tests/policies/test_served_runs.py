"""A policy behind a server, evaluated by the harness end to end (issue 73's "done when"): `octo-harness serve` on the
robosuite reference (deterministic: an L1 head) and Lift through `--model ws://`, sequentially and with `--workers 2`;
the server killed mid-run, started again on another port and the run resumed in the same folder; `compare` against
the in-process run of the same checkpoint says IDENTICAL each time. And the standalone server script (no harness
imports) wrapping the scripted Lift expert, evaluated end to end."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import REFERENCE_MODEL, REPO
from tests.policies.test_policy_server import Server, serve

pytestmark = pytest.mark.slow
RUN = ["--task", "Lift", "--episodes", "2", "--max-steps", "8", "--seed", "3", "--png-every", "0", "--fast-render"]


def harness(*argv: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "harness.cli", *argv], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def compare(baseline: Path, candidate: Path, out: Path) -> dict:
    done = harness("compare", str(baseline), str(candidate), "--out", str(out))
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads((out / "compare.json").read_text())


def only_run(folder: Path) -> Path:
    (run,) = [p for p in folder.iterdir() if (p / "manifest.json").is_file()]
    return run


def rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "results.jsonl").read_text().splitlines() if line.strip()]


@pytest.fixture(scope="module")
def local(tmp_path_factory) -> Path:
    """The in-process run of the reference: what every served run must equal."""
    out = tmp_path_factory.mktemp("local")
    done = harness("run", "--model", str(REFERENCE_MODEL), *RUN, "--out", str(out))
    assert done.returncode == 0, done.stderr[-2000:]
    return only_run(out)


@pytest.fixture(scope="module")
def server():
    started = serve().wait_ready()
    yield started
    started.stop()


@pytest.fixture(scope="module")
def standalone():
    """The standalone server script (no harness imports) around its default policy, the blind scripted Lift expert."""
    started = Server([sys.executable, str(REPO / "examples" / "serve" / "standalone_server.py"), "--port", "0"])
    yield started.wait_ready()
    started.stop()


def test_a_served_run_equals_the_in_process_run_sequentially_and_with_two_workers(local, server, tmp_path):
    for name, extra in (("sequential", []), ("workers", ["--workers", "2"])):
        out = tmp_path / name
        done = harness("run", "--model", server.url, *RUN, "--out", str(out), *extra)
        assert done.returncode == 0, done.stderr[-2000:]
        run = only_run(out)
        assert run.name.startswith("served_")  # named by what is served, not where
        manifest = json.loads((run / "manifest.json").read_text())
        assert manifest["protocol"]["model"] == "ws://"  # the address is outside the protocol and its hash
        assert manifest["model"]["server"]["fingerprint"] == server.ready.split("(fingerprint ", 1)[1].split(")")[0]
        assert manifest["model"]["layers"] is None and "served" in manifest["protocol"]["model_fingerprint"] or \
            manifest["protocol"]["model_fingerprint"].startswith("sha256:")
        # the conventions came from the server: the checkpoint's action space and dataset key
        assert manifest["protocol"]["env"]["action_space"] == "robosuite"
        finding = [f for f in manifest["preflight"]["findings"] if f["check"] == "action"][0]
        assert finding["verdict"] == "consistent" and "evidence" not in finding  # the statistics the server declared
        for a, b in zip(sorted(local.rglob("actions.npz")), sorted(run.rglob("actions.npz"))):
            with np.load(a) as x, np.load(b) as y:
                assert np.array_equal(x["executed"], y["executed"]) and np.array_equal(x["predicted"], y["predicted"])
        result = compare(local, run, tmp_path / f"compare-{name}")
        assert result["verdict"] == "IDENTICAL", result["verdict"]


def test_a_server_killed_mid_run_is_an_infrastructure_failure_and_a_restarted_one_resumes_the_run(local, server,
                                                                                                   standalone, tmp_path):
    """With --workers 2: the driver's one connection is lost under both workers' episodes (the sequential path's
    ServerLostError is an infrastructure failure by harness.run.executor.failure_of: test_served_client.py)."""
    first = serve().wait_ready()
    out = tmp_path / "killed"
    argv = [sys.executable, "-m", "harness.cli", "run", "--model", first.url, *RUN, "--out", str(out), "--retries", "0",
            "--workers", "2"]
    running = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        # kill the server once the episodes are under way (their folders exist: each worker has reset its env and
        # asks for actions); waiting for a finished row raced with --workers 2, whose other episode could be done too
        while time.monotonic() < deadline and running.poll() is None:
            if len(list(out.glob("*/Lift/episode_*"))) >= 2:
                break
            time.sleep(0.05)
        first.stop(signal.SIGKILL)
        _, err = running.communicate(timeout=240)
    finally:
        first.stop(signal.SIGKILL)
    run = only_run(out)
    lost = [r for r in rows(run) if r["status"] == "failed"]
    assert running.returncode != 0 or lost, err[-2000:]
    assert all(r["failure"] == "infrastructure" and r["lost"] == "policy server" for r in lost), lost
    assert lost, "the server died after the run had finished: nothing was lost"
    assert server.url != first.url  # another server process on another port: the same policy
    done = harness("run", "--model", server.url, *RUN, "--out", str(out))
    assert done.returncode == 0, done.stderr[-2000:]
    assert only_run(out) == run  # the same folder: the address is not part of the protocol
    assert sorted((r["episode"], r["status"]) for r in rows(run)[-2:]) == [(0, "ok"), (1, "ok")] or \
        {r["episode"] for r in rows(run) if r["status"] == "ok"} == {0, 1}
    assert compare(local, run, tmp_path / "compare")["verdict"] == "IDENTICAL"
    # another policy behind an address is another protocol: the folder is not resumed with it
    done = harness("run", "--model", standalone.url, *RUN, "--out", str(out), "--run-name", run.name)
    assert done.returncode == 2 and "differs" in done.stderr and "model_fingerprint" in done.stderr, done.stderr[-800:]


EXPERT_CONVENTIONS = REPO / "examples" / "serve" / "scripted_lift.toml"


@pytest.fixture(scope="module")
def expert_run(standalone, tmp_path_factory) -> Path:
    """One run of the blind scripted Lift expert through the standalone script, with its conventions file (its
    replies are deterministic: test_policy_server.py sends one observation twice)."""
    out = tmp_path_factory.mktemp("expert")
    done = harness("run", "--model", standalone.url, "--task", "Lift", "--episodes", "1", "--max-steps", "16",
                   "--seed", "0", "--png-every", "0", "--fast-render", "--out", str(out), "--run-name", "a",
                   "--served-conventions", str(EXPERT_CONVENTIONS),
                   "--action-consistency")  # computed from the chunks: any policy with action chunks records it
    assert done.returncode == 0, done.stderr[-2000:]
    return out / "a"


def test_the_standalone_server_script_serves_the_scripted_expert_end_to_end(expert_run):
    run = expert_run
    (episode,) = run.rglob("actions.npz")
    with np.load(episode) as actions:
        executed = actions["executed"]
    assert executed.shape == (16, 7) and np.isfinite(executed).all()
    assert np.abs(executed[:, :3]).max() > 0.1  # the expert moves (robosuite's controller inputs)
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["model"]["server"]["name"] == "blind-scripted-lift"
    finding = [f for f in manifest["preflight"]["findings"] if f["check"] == "action"][0]
    assert finding["evidence"] == "first chunk" and finding["verdict"] != "MISMATCH", finding  # no statistics served
    meta = json.loads(next(run.rglob("episode.json")).read_text())
    assert meta.get("attention") is False  # a policy without attention: recorded as such
    assert (episode.parent / "rollout.mp4").stat().st_size > 0  # the frames, without overlay panels
    from harness.probes.action_consistency import reader

    stored, computed = reader.arrays(episode.parent), reader.from_actions(episode.parent)
    assert stored is not None and len(stored["step"]) > 1 and np.array_equal(stored["step"], computed["step"])
    assert np.allclose(stored["disagreement"], computed["disagreement"], equal_nan=True)
    assert np.isfinite(stored["disagreement"][1:]).all()  # every inferred chunk after the first overlaps a plan


def test_a_robustness_grid_of_a_served_policy_takes_its_conventions(standalone, expert_run, tmp_path):
    """`robustness --served-conventions FILE` (it was `run` only): every run of the grid maps the observations with the
    file, and its nominal run is the same protocol as `run` with the same server and file (the model fingerprint
    holds the file's content)."""
    done = harness("robustness", "--model", standalone.url, "--task", "Lift", "--perturb", "lighting", "--levels", "0,1",
                   "--episodes", "1", "--max-steps", "8", "--fast-render", "--out", str(tmp_path),
                   "--served-conventions", str(EXPERT_CONVENTIONS))
    assert done.returncode == 0, done.stderr[-2000:]
    from harness.policies.served import server_identity

    made = json.loads((expert_run / "manifest.json").read_text())["protocol"]
    for name in ("nominal", "lighting-1"):
        manifest = json.loads((tmp_path / name / "manifest.json").read_text())
        fingerprint = manifest["protocol"]["model_fingerprint"]
        assert fingerprint == made["model_fingerprint"], name
        assert fingerprint != server_identity(manifest["model"]["fingerprint"]["metadata"])  # not the server's own
        assert len(rows(tmp_path / name)) == 1 and rows(tmp_path / name)[0]["status"] == "ok"


def test_a_flag_needing_what_a_served_policy_lacks_is_one_line_before_any_episode(server, tmp_path):
    done = harness("run", "--model", server.url, *RUN, "--out", str(tmp_path), "--reliance-every", "4")
    errors = [line for line in done.stderr.splitlines() if line.startswith("error: ")]
    assert done.returncode == 2 and len(errors) == 1 and "--reliance-every" in errors[0] and "declares no" in errors[0]
    assert not list(tmp_path.rglob("results.jsonl"))  # nothing ran
    from harness.policies import PolicyLacksError, load_policy
    from harness.run.checks import check_attention_flags
    from harness.run.settings import build_protocol

    policy = load_policy(server.url)
    try:
        base = {"model": server.url, "task": ["Lift"], "png_every": 0}
        assert check_attention_flags(build_protocol(base), policy)  # the line saying what it leaves out, no error
        drawn = {"layers": "0", "png_every": 4, "cmap": "jet", "bbox": True}  # how attention is drawn: left out
        assert "whatever the output options say" in check_attention_flags(build_protocol({**base, **drawn}), policy)[0]
        for extra, flag in (({"intervene": "mask-all"}, "--intervene"),
                            ({"video_attention": "rollout"}, "--video-attention rollout"),
                            ({"readout_features_every": 1}, "--readout-features-every")):
            with pytest.raises(PolicyLacksError, match=flag):
                check_attention_flags(build_protocol({**base, **extra}), policy)
        # action consistency is computed from the chunks, for any policy: only its extra draws need the policy
        assert check_attention_flags(build_protocol({**base, "action_consistency": True}), policy)
        with pytest.raises(PolicyLacksError, match="--action-samples 4"):
            check_attention_flags(build_protocol({**base, "action_consistency": True, "action_samples": 4}), policy)
    finally:
        policy.close()


def test_served_conventions_are_refused_for_a_checkpoint(tmp_path):
    done = harness("run", "--model", str(REFERENCE_MODEL), *RUN, "--out", str(tmp_path), "--served-conventions",
                   str(REPO / "examples" / "serve" / "scripted_lift.toml"))
    assert done.returncode == 2 and "--served-conventions is for a policy behind a server" in done.stderr


def test_replay_of_the_committed_baseline_through_the_server_is_equivalent_on_actions(server, tmp_path):
    """The gate's replay step with a served candidate: the baseline's recorded inputs sent through ws://, its chunks
    within the tolerances; attention is not compared (one note), never reported as measured."""
    done = harness("replay", str(REPO / "results" / "baselines" / "reference-lift"), "--model", server.url,
                   "--out", str(tmp_path))
    assert done.returncode == 0, done.stdout[-1500:] + done.stderr[-1500:]
    replay = json.loads((tmp_path / "replay.json").read_text())
    assert replay["verdict"] == "EQUIVALENT" and replay["attention_js_max"] is None
    episodes = replay["episode_details"]
    assert episodes and all(e["note"] == "the replayed policy gives no attention: actions compared only"
                            and e["attention_js_max"] is None and e["action_change_max"] <= 3e-4 for e in episodes)


def test_view_re_simulates_a_served_run_only_with_its_server_and_conventions(standalone, expert_run, tmp_path):
    """A run records neither its server's address nor its conventions file: `view` without --model names the flag
    in one line (it named a flag view did not have), and with both re-simulates the episode bit for bit. Without
    the conventions the server's own metadata holds (one action a chunk, no temporal ensemble): the actions differ,
    and the frames note says so, so the file is what was used."""
    done = harness("view", str(expert_run), "--save", str(tmp_path / "none.rrd"))
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr[-800:]
    assert "--model ws://HOST:PORT" in done.stderr and "--no-simulate" in done.stderr
    done = harness("view", str(expert_run), "--save", str(tmp_path / "both.rrd"), "--model", standalone.url,
                   "--served-conventions", str(EXPERT_CONVENTIONS))
    assert done.returncode == 0 and "equal the recorded ones bit for bit" in done.stdout, done.stdout + done.stderr[-800:]
    assert (tmp_path / "both.rrd").stat().st_size > 0
    done = harness("view", str(expert_run), "--save", str(tmp_path / "bare.rrd"), "--model", standalone.url)
    assert done.returncode == 0 and "differ from the recorded ones" in done.stdout, done.stdout + done.stderr[-800:]
    # the conventions file alone, or with --no-simulate, loads nothing: one line each, before anything heavy
    for extra in (["--served-conventions", str(EXPERT_CONVENTIONS)],
                  ["--model", standalone.url, "--served-conventions", str(EXPERT_CONVENTIONS), "--no-simulate"]):
        done = harness("view", str(expert_run), "--save", str(tmp_path / "x.rrd"), *extra)
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr[-800:]
        assert not (tmp_path / "x.rrd").exists()
    done = harness("view", str(expert_run), "--save", str(tmp_path / "y.rrd"), "--model", standalone.url,
                   "--served-conventions", str(tmp_path / "missing.toml"))
    assert done.returncode == 2 and "missing.toml" in done.stderr and "--served-conventions" in done.stderr

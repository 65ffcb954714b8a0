"""Run store units (no simulator, no model): protocol round trip and diff, protocol files, the lock, results.jsonl
repair and write failures, derived tables. Each asserts behaviour a user relies on when a run is resumed or shared."""

import csv
import errno
import json
import multiprocessing
import os
import signal

import pytest

from envs.options import EnvOptions
from harness.policy import PolicyConfig
from harness.run.protocol import EpisodeJob, Protocol, diff, model_fingerprint
from harness.run.settings import build_protocol, read_protocol_file, resolve_tasks
from harness.run.store import EpisodeRow, ResultsWriteError, RunLockedError, RunStore
from harness.outputs.writers import OutputOptions


def _protocol(**kw) -> Protocol:
    base = dict(model="random:octo-small-1.5", tasks=("Lift", "Stack"), episodes=3, seed=10)
    return Protocol(**{**base, **kw})


def test_protocol_round_trips_through_its_dict_and_lists_jobs():
    p = _protocol(env=EnvOptions(masks=True, cameras=(("image_primary", "agentview", 84),), action_space="robosuite"),
                  policy=PolicyConfig(execution="receding_horizon", receding_steps=2),
                  outputs=OutputOptions(png_every=0, layers=(0, -1)))
    d = json.loads(json.dumps(p.to_dict()))
    assert d["execution"] == "receding_horizon:2" and d["env"]["cameras"] == {"image_primary": ["agentview", 84]}
    back = Protocol.from_dict(d)
    assert back == p and back.hash() == p.hash()
    assert p.jobs()[:4] == [EpisodeJob("Lift", 0, 10), EpisodeJob("Lift", 1, 11), EpisodeJob("Lift", 2, 12),
                            EpisodeJob("Stack", 0, 10)]
    assert EpisodeJob("Lift", 2, 12).directory == "Lift/episode_2"


def test_diff_names_nested_fields_with_dots():
    a = _protocol()
    b = _protocol(episodes=4, policy=PolicyConfig(ensemble_weight=0.5), env=EnvOptions(masks=True, fast_render=True))
    assert diff(a.to_dict(), b.to_dict()) == ["env.fast_render", "episodes", "policy.ensemble_weight"]
    assert diff(a.to_dict(), a.to_dict()) == []
    assert a.hash() != b.hash()


def test_protocol_from_dict_rejects_unknown_fields():
    d = _protocol().to_dict()
    with pytest.raises(ValueError, match="newer"):
        Protocol.from_dict({**d, "surprise": 1})


@pytest.mark.parametrize("kw,needle", [
    (dict(episodes=0), "--episodes"), (dict(max_steps=-5), "--max-steps"), (dict(max_steps=0), "--max-steps"),
    (dict(tasks=()), "--task"), (dict(seed=-1), "--seed"),
])
def test_protocol_numbers_are_checked_with_one_line(kw, needle):
    with pytest.raises(ValueError) as err:
        _protocol(**kw)
    assert needle in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("kw,needle", [
    (dict(ensemble_weight=float("nan")), "--ensemble-weight"), (dict(ensemble_weight=float("inf")), "--ensemble-weight"),
    (dict(receding_steps=0), "--receding-steps"), (dict(attention_controls="blank", controls_every=0), "--controls-every"),
])
def test_policy_numbers_are_checked_once_where_they_are_declared(kw, needle):
    with pytest.raises(ValueError) as err:  # PolicyConfig's own check; the settings layer and Protocol only convert
        PolicyConfig(**kw)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_receding_steps_default_is_the_field_s_and_the_ensemble_records_one():
    assert PolicyConfig(execution="receding_horizon").receding_steps == 4  # the help's [4] is the field's default
    assert PolicyConfig().receding_steps == 1 and PolicyConfig().to_dict()["receding_steps"] == 1  # hashes unchanged


def test_tasks_match_case_insensitively_without_duplicates():
    assert resolve_tasks(["lift,STACK", "Lift", " stack "]) == ("Lift", "Stack")
    with pytest.raises(ValueError, match="--task"):
        resolve_tasks([""])
    with pytest.raises(ValueError, match="Lift"):  # names the closest registered task
        resolve_tasks(["Lfit"])


def test_model_fingerprint_hashes_the_loaded_files(fixtures_dir, tmp_path):
    fp, details = model_fingerprint(str(fixtures_dir / "tiny"))
    assert fp.startswith("sha256:") and {"config.json", "300000/default/checkpoint"} <= set(details["files"])
    assert model_fingerprint("random:octo-small-1.5")[0].startswith("preset:octo-small-1.5+")  # + its tokenizer
    # a changed byte in the parameters changes the fingerprint
    copy = tmp_path / "tiny"
    import shutil

    shutil.copytree(fixtures_dir / "tiny", copy)
    blob = copy / "300000" / "default" / "checkpoint"
    os.chmod(blob, 0o644)
    data = bytearray(blob.read_bytes())
    data[-1] ^= 1
    blob.write_bytes(bytes(data))
    assert model_fingerprint(str(copy))[0] != fp


def test_the_figures_beside_a_models_eval_md_are_not_part_of_its_fingerprint(fixtures_dir, tmp_path):
    """An EVAL.md section's figures file (figures/<section>.json, written beside the model) is a result about the
    checkpoint: writing one left every committed baseline of that model stale once (its fingerprint changed)."""
    import shutil

    copy = tmp_path / "tiny"
    shutil.copytree(fixtures_dir / "tiny", copy)
    fp = model_fingerprint(str(copy))[0]
    (copy / "figures").mkdir()
    (copy / "figures" / "robustness.json").write_text("{}")
    assert model_fingerprint(str(copy))[0] == fp
    (copy / "tokenizer").mkdir()  # any other folder beside the steps is read by loading (tokenizer, T5 config)
    (copy / "tokenizer" / "vocab.txt").write_text("a b")
    assert model_fingerprint(str(copy))[0] != fp


def test_protocol_file_keys_mirror_flags_and_flags_override(tmp_path):
    path = tmp_path / "eval.toml"
    path.write_text('task = ["lift", "Stack"]\nmodel = "random:octo-small-1.5"\nepisodes = 5\nmax-steps = 20\n'
                    'execution = "receding_horizon"\nfast_render = true\npng_every = 0\n'
                    'camera = ["image_primary=agentview:84"]\naction_space = "robosuite"\n')
    settings = read_protocol_file(path)
    p = build_protocol({**settings, "episodes": 2})  # a flag given on the command line wins
    assert p.tasks == ("Lift", "Stack") and p.episodes == 2 and p.max_steps == 20
    assert p.policy.execution == "receding_horizon" and p.policy.receding_steps == 4
    assert p.env.fast_render and p.env.masks and p.env.cameras == (("image_primary", "agentview", 84),)
    assert p.env.action_space == "robosuite" and p.outputs.png_every == 0


def test_protocol_file_unknown_keys_are_one_line(tmp_path):
    path = tmp_path / "eval.toml"
    path.write_text('task = "Lift"\nepisodez = 5\ncolour = "red"\n')
    with pytest.raises(ValueError) as err:
        read_protocol_file(path)
    message = str(err.value)
    assert "\n" not in message and "colour" in message and "episodez" in message
    path.write_text('task = "Lift"\nepisodes = "five"\n')
    with pytest.raises(ValueError, match="episodes must be a int"):
        read_protocol_file(path)


def _row(task="Lift", k=0, status="ok", success=True):
    job = EpisodeJob(task, k, k)
    if status != "ok":
        return EpisodeRow.failed("r", job, "RuntimeError: boom")
    return EpisodeRow("r", task, k, k, "ok", success, 5, 1.0, 0.1, 0.05, 0.04, 0.1, job.directory)


def test_second_lock_names_the_holder_pid(tmp_path):
    first = RunStore(tmp_path / "r")
    first.lock()
    try:
        with pytest.raises(RunLockedError) as err:
            RunStore(tmp_path / "r").lock()
        assert f"process {os.getpid()}" in str(err.value) and "\n" not in str(err.value)
    finally:
        first.unlock()
    with RunStore(tmp_path / "r"):  # released: can be taken again
        pass


def _hold_lock_forever(path, ready):
    RunStore(path).lock()
    ready.set()
    signal.pause()


def test_lock_of_a_killed_process_does_not_block(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    ready = ctx.Event()
    child = ctx.Process(target=_hold_lock_forever, args=(tmp_path / "r", ready))
    child.start()
    try:
        assert ready.wait(60)
        with pytest.raises(RunLockedError, match=str(child.pid)):
            RunStore(tmp_path / "r").lock()
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.join(30)
    with RunStore(tmp_path / "r") as store:
        assert (store.dir / ".lock").read_text().strip() == str(os.getpid())


def test_results_jsonl_append_repair_and_last_line_wins(tmp_path):
    store = RunStore(tmp_path / "r")
    with store:
        store.append(_row(k=0, status="failed"))
        store.append(_row(k=1))
        store.append(_row(k=0))  # rerun of a failed job: the last line wins
        with open(store.dir / "results.jsonl", "ab") as f:
            f.write(b'{"run": "r", "task": "Li')  # a line torn by SIGKILL
        rows = store.load_rows()
        assert {k: r.status for k, r in rows.items()} == {("Lift", 0): "ok", ("Lift", 1): "ok"}
        assert (store.dir / "results.jsonl").read_bytes().endswith(b"}\n")  # the torn line is cut off
        store.append(_row(k=2))
        assert len(store.load_rows()) == 3


def test_failed_append_is_one_line_naming_path_and_os_error(tmp_path, monkeypatch):
    store = RunStore(tmp_path / "r")
    with store:
        store.append(_row(k=0))

        def full(fd, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(os, "write", full)
        with pytest.raises(ResultsWriteError) as err:
            store.append(_row(k=1))
        monkeypatch.undo()
        message = str(err.value)
        assert "\n" not in message and str(store.dir / "results.jsonl") in message and "No space left" in message
        assert list(store.load_rows()) == [("Lift", 0)]  # consistent: the first row only


def test_derived_tables_hold_rows_in_job_order_with_wilson_intervals(tmp_path):
    store = RunStore(tmp_path / "r")
    jobs = [EpisodeJob("Lift", k, k) for k in range(3)] + [EpisodeJob("Stack", k, k) for k in range(3)]
    rows = {r.key: r for r in [_row("Stack", 0, success=False), _row("Lift", 1), _row("Lift", 0, success=False),
                               _row("Lift", 2, status="failed")]}
    with store:
        store.write_derived({"run": "r"}, jobs, rows, "running")
    results = json.loads((store.dir / "results.json").read_text())
    assert results["status"] == "running" and results["missing"] == 2
    assert [(e["task"], e["episode"]) for e in results["episodes"]] == [("Lift", 0), ("Lift", 1), ("Lift", 2), ("Stack", 0)]
    lift = results["statistics"]["tasks"]["Lift"]
    assert (lift["n"], lift["successes"], lift["failed"]) == (2, 1, 1)  # the failed episode is not counted in n
    assert (round(lift["ci_low"], 4), round(lift["ci_high"], 4)) == (0.0945, 0.9055)  # Wilson 1/2
    overall = results["statistics"]["overall"]
    assert (overall["n"], overall["successes"], overall["failed"]) == (3, 1, 1)
    with open(store.dir / "summary.csv") as f:
        table = list(csv.DictReader(f))
    assert [r["directory"] for r in table] == ["Lift/episode_0", "Lift/episode_1", "Lift/episode_2", "Stack/episode_0"]
    assert table[2]["status"] == "failed" and table[2]["error"] == "RuntimeError: boom" and table[2]["return"] == ""
    assert {"run", "task", "episode", "seed", "success", "steps", "return", "seconds_per_step"} <= set(table[0])
    with open(store.dir / "statistics.csv") as f:
        stats = {r["task"]: r for r in csv.DictReader(f)}
    assert set(stats) == {"Lift", "Stack", "overall"} and stats["Stack"]["successes"] == "0"
    assert float(stats["Lift"]["ci_high"]) == pytest.approx(0.9055, abs=1e-4)


def test_progress_prints_one_line_per_episode_with_successes_and_eta_when_not_a_terminal():
    import io

    from harness.run.progress import Progress

    stream = io.StringIO()
    progress = Progress(total=4, done=1, successes=1, stream=stream)
    assert progress.bar is None  # not a terminal: no bar, plain lines
    progress.episode(_row(k=1, success=False))
    progress.episode(_row(k=2, status="failed"))
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("[2/4] Lift/episode_1: no success") and "success 1/2" in lines[0] and "ETA" in lines[0]
    assert lines[1].startswith("[3/4] Lift/episode_2: FAILED") and "success 1/3" in lines[1]


def test_checkpoint_conventions_fill_what_the_user_did_not_give(fixtures_dir, tmp_path):
    import shutil

    from harness.conventions import CheckpointConventions

    ckpt = tmp_path / "ckpt"
    shutil.copytree(fixtures_dir / "tiny", ckpt)
    os.chmod(ckpt, 0o755)
    CheckpointConventions(env={"cameras": {"image_primary": ["agentview", 84]}, "action_space": "robosuite"},
                          policy={"execution": "receding_horizon", "receding_steps": 2}).write(ckpt)
    p = build_protocol({"task": ["Lift"], "model": str(ckpt)})
    assert p.env.cameras == (("image_primary", "agentview", 84),) and p.env.action_space == "robosuite"
    assert p.policy.execution == "receding_horizon" and p.policy.receding_steps == 2
    # flags (or protocol-file keys) win over the checkpoint's conventions
    p = build_protocol({"task": ["Lift"], "model": str(ckpt), "camera": ["image_primary=agentview:96"],
                        "receding_steps": 3, "action_space": "octo-delta"})
    assert p.env.cameras == (("image_primary", "agentview", 96),) and p.env.action_space == "octo-delta"
    assert p.policy.receding_steps == 3
    assert model_fingerprint(str(ckpt))[1]["files"].keys() >= {"harness.toml"}  # conventions are part of the model

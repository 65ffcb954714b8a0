"""Run folders are untrusted input (issue 28): each attack a hostile user tried, on real runs (the tiny reference
fixture model in the real simulator, and copies of the committed baseline), is refused with one line naming the
file (exit 2) by every reader, or repaired by `run --resume`, which runs the damaged episode again.

A row naming a folder outside the run, an episode folder linked outside, deleted, cut-short or corrupted arrays, a
results.jsonl that is a symlink loop, an episode folder replaced by a self-symlink. The tests on the tiny run are
marked slow (they make a run and resume it: about 3 minutes on 2 cores); those on the baseline's copies are quick.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from envs.options import EnvOptions
from harness import cli
from harness.analysis.runs import load_run
from harness.outputs.writers import OutputOptions
from harness.run import Protocol, execute
from harness.runfolder.integrity import file_digest
from tests.runfolder.edits import make_legacy, rehash

REPO = Path(__file__).resolve().parents[2]
BASELINE = REPO / "results" / "baselines" / "reference-lift"
STEPS = 2


@pytest.fixture(scope="module")
def made(fixtures_dir, tmp_path_factory):
    """A real run of the tiny model (2 Lift episodes, 2 steps, recorded inputs). The resumes below load the model
    again from the suite's persistent compilation cache (tests/conftest.py), not a fresh compile."""
    from harness.octo import load_pretrained

    out = tmp_path_factory.mktemp("made")
    model = load_pretrained(str(fixtures_dir / "tiny"))
    protocol = Protocol(model=str(fixtures_dir / "tiny"), tasks=("Lift",), episodes=2, max_steps=STEPS,
                        env=EnvOptions(masks=False, fast_render=True),
                        outputs=OutputOptions(png_every=0, video=False, record_inputs=True))
    execute(protocol, out, "run", model=model, progress=False)
    return out / "run"


@pytest.fixture()
def runs(made, tmp_path):
    """Fresh copies of the tiny run: (good, bad, outside) where `outside` is another run next to them."""
    copies = [tmp_path / name for name in ("good", "bad", "outside")]
    for copy in copies:
        shutil.copytree(made, copy, symlinks=True)
    return tuple(copies)


def _commands(good: Path, bad: Path, tmp: Path, model: str) -> dict[str, list[str]]:
    return {
        "report": ["report", str(bad), "--out", str(tmp / "report")],
        "compare (candidate)": ["compare", str(good), str(bad), "--no-frames", "--out", str(tmp / "cmp")],
        "compare (baseline)": ["compare", str(bad), str(good), "--no-frames", "--out", str(tmp / "cmp")],
        "regress --baseline": ["regress", "--baseline", str(bad), "--model", model, "--out", str(tmp / "reg")],
        "replay": ["replay", str(bad), "--out", str(tmp / "replay")],
    }


def _one_line_exit_2(argv, capsys, *expected: str) -> str:
    try:
        code = cli.main(argv)
    except SystemExit as exc:  # argparse's own errors end the process (exit 2)
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, (argv[0], code, err)
    assert len(err) == 1 and err[0].startswith("error: "), (argv[0], err)
    for text in expected:
        assert text in err[0], (argv[0], err)
    return err[0]


def _rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "results.jsonl").read_text().splitlines() if line.strip()]


def _write_rows(run: Path, rows: list[dict]) -> None:
    (run / "results.jsonl").write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in rows))


def _resume(run: Path, capsys, *extra: str, caplog=None) -> tuple[int, str, str]:
    """exit code, stdout, and stderr with the log lines (the command line prints them on stderr; pytest captures them)."""
    if caplog is not None:
        caplog.clear()
    code = cli.main(["run", "--resume", str(run), *extra])
    captured = capsys.readouterr()
    logged = "".join(f"{r.getMessage()}\n" for r in caplog.records) if caplog is not None else ""
    return code, captured.out, captured.err + logged


# ---- what a finished episode records -----------------------------------------------------------------------------

@pytest.mark.slow
def test_each_finished_episode_records_size_and_sha256_of_its_data_files(made):
    for row in _rows(made):
        folder = made / row["directory"]
        assert row["status"] == "ok" and sorted(row["files"]) == ["actions.npz", "attention.npz", "inputs.npz",
                                                                  "metrics.jsonl"]
        for name, recorded in row["files"].items():
            assert recorded == file_digest(folder / name) and recorded["size"] == (folder / name).stat().st_size
    assert load_run(made).unverified == 0


# ---- a run folder that points outside itself ---------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("where", ["relative", "absolute"])
def test_a_row_naming_a_folder_outside_the_run_is_refused_everywhere(runs, tmp_path, capsys, fixtures_dir, where):
    good, bad, outside = runs
    rows = _rows(bad)
    target = outside / "Lift" / "episode_1"
    rows[0]["directory"] = "../outside/Lift/episode_1" if where == "relative" else str(target)
    _write_rows(bad, rows)
    for name, argv in _commands(good, bad, tmp_path, str(fixtures_dir / "tiny")).items():
        _one_line_exit_2(argv, capsys, "results.jsonl line 1", "directory must be the job's folder Lift/episode_0")
    code, out, err = _resume(bad, capsys)
    assert code == 2 and "directory must be the job's folder" in err and "already finished" not in out
    assert not (tmp_path / "reg").exists() and not (tmp_path / "report").exists()


@pytest.mark.slow
def test_an_episode_folder_linked_outside_is_refused_by_readers_and_rerun_by_resume(runs, tmp_path, capsys, caplog,
                                                                                      fixtures_dir):
    good, bad, outside = runs
    episode = bad / "Lift" / "episode_0"
    shutil.rmtree(episode)
    episode.symlink_to(outside / "Lift" / "episode_1")  # another run's episode, with files that parse
    for name, argv in _commands(good, bad, tmp_path, str(fixtures_dir / "tiny")).items():
        _one_line_exit_2(argv, capsys, "Lift/episode_0 is a symlink")
    before = {p: p.read_bytes() for p in (outside / "Lift" / "episode_1").iterdir()}
    code, out, err = _resume(bad, capsys, caplog=caplog)
    assert code == 0 and "is a symlink" in err and "running episode Lift/episode_0 again" in err
    assert "resumed: 1 of 2" in out
    assert not episode.is_symlink() and episode.is_dir()
    assert {p: p.read_bytes() for p in (outside / "Lift" / "episode_1").iterdir()} == before  # never followed
    _same_files(episode, good / "Lift" / "episode_0")


@pytest.mark.slow
def test_a_task_folder_linked_outside_leads_outside(runs, tmp_path, capsys):
    good, bad, outside = runs
    shutil.rmtree(bad / "Lift")
    (bad / "Lift").symlink_to(outside / "Lift")
    _one_line_exit_2(["compare", str(good), str(bad), "--no-frames", "--out", str(tmp_path / "cmp")], capsys,
                     "Lift is a symlink")


@pytest.mark.slow
def test_a_file_inside_an_episode_linked_outside_is_refused(runs, tmp_path, capsys):
    good, bad, outside = runs
    (bad / "Lift" / "episode_0" / "extra.png").symlink_to(outside / "manifest.json")
    _one_line_exit_2(["report", str(bad), "--out", str(tmp_path / "report")], capsys,
                     "extra.png", "leads outside the run folder")


@pytest.mark.slow
def test_results_jsonl_as_a_symlink_loop_is_one_line_exit_2(runs, tmp_path, capsys, fixtures_dir):
    good, bad, _ = runs
    (bad / "results.jsonl").unlink()
    (bad / "results.jsonl").symlink_to(bad / "results.jsonl")
    for name, argv in _commands(good, bad, tmp_path, str(fixtures_dir / "tiny")).items():
        _one_line_exit_2(argv, capsys, "results.jsonl is a symlink loop")
    code, _, err = _resume(bad, capsys)
    assert code == 2 and "results.jsonl is a symlink loop" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_manifest_linked_outside_is_refused(runs, tmp_path, capsys):
    good, bad, outside = runs
    (bad / "manifest.json").unlink()
    (bad / "manifest.json").symlink_to(outside / "manifest.json")
    _one_line_exit_2(["report", str(bad), "--out", str(tmp_path / "report")], capsys, "manifest.json",
                     "leads outside the run folder")
    code, _, err = _resume(bad, capsys)
    assert code == 2 and "leads outside the run folder" in err


# ---- damaged finished episodes -----------------------------------------------------------------------------------

def _same_files(a: Path, b: Path) -> None:
    for name in ("actions.npz", "attention.npz", "inputs.npz"):
        with np.load(a / name) as za, np.load(b / name) as zb:
            assert za.files == zb.files and all(np.array_equal(za[k], zb[k]) for k in za.files), name


@pytest.mark.slow
def test_a_deleted_actions_npz_is_named_by_readers_and_rerun_by_resume(runs, tmp_path, capsys, caplog, fixtures_dir):
    good, bad, _ = runs
    (bad / "Lift" / "episode_1" / "actions.npz").unlink()
    for name, argv in _commands(good, bad, tmp_path, str(fixtures_dir / "tiny")).items():
        _one_line_exit_2(argv, capsys, "episode_1/actions.npz is missing", "octo-harness run --resume")
    code, out, err = _resume(bad, capsys, caplog=caplog)
    assert code == 0 and "episode_1/actions.npz is missing; running episode Lift/episode_1 again" in err
    assert "resumed: 1 of 2 episodes were already finished" in out
    _same_files(bad / "Lift" / "episode_1", good / "Lift" / "episode_1")
    assert load_run(bad).status == "complete"
    assert cli.main(["compare", str(good), str(bad), "--no-frames", "--out", str(tmp_path / "cmp")]) == 0


@pytest.mark.slow
def test_corrupt_attention_and_half_truncated_actions_are_rerun_on_resume(runs, tmp_path, capsys, caplog):
    good, bad, _ = runs
    attention = bad / "Lift" / "episode_0" / "attention.npz"
    data = bytearray(attention.read_bytes())
    data[len(data) // 2] ^= 0xFF  # same size, one byte flipped: only the digest sees it
    attention.write_bytes(bytes(data))
    actions = bad / "Lift" / "episode_1" / "actions.npz"
    actions.write_bytes(actions.read_bytes()[: actions.stat().st_size // 2])
    _one_line_exit_2(["compare", str(good), str(bad), "--no-frames", "--out", str(tmp_path / "cmp")], capsys,
                     "episode_0/attention.npz is damaged (its sha256 differs")
    _one_line_exit_2(["replay", str(bad), "--out", str(tmp_path / "replay")], capsys, "attention.npz is damaged")
    code, out, err = _resume(bad, capsys, caplog=caplog)
    assert code == 0 and "resumed" not in out  # nothing was left standing: both episodes ran again
    assert "attention.npz is damaged" in err and "actions.npz is damaged (" in err and "bytes, its row records" in err
    for k in (0, 1):
        _same_files(bad / "Lift" / f"episode_{k}", good / "Lift" / f"episode_{k}")
    assert load_run(bad).status == "complete"


@pytest.mark.slow
def test_digests_stripped_from_a_row_do_not_hide_a_deleted_array(runs, tmp_path, capsys):
    """files = {} would verify nothing: a row with digests must record those of the arrays every episode writes."""
    good, bad, _ = runs
    rows = _rows(bad)
    rows[0]["files"] = {}
    _write_rows(bad, rows)
    (bad / "Lift" / "episode_0" / "attention.npz").unlink()
    _one_line_exit_2(["compare", str(good), str(bad), "--no-frames", "--out", str(tmp_path / "cmp")], capsys,
                     "its row records no digest of attention.npz")


@pytest.mark.slow
def test_an_episode_folder_replaced_by_a_self_symlink_is_rerun(runs, capsys, caplog):
    _, bad, _ = runs
    episode = bad / "Lift" / "episode_0"
    shutil.rmtree(episode)
    episode.symlink_to(episode)
    code, out, err = _resume(bad, capsys, "--retry-failed", caplog=caplog)
    assert code == 0 and "running episode Lift/episode_0 again" in err
    assert episode.is_dir() and not episode.is_symlink() and load_run(bad).status == "complete"


@pytest.mark.slow
def test_a_failed_episode_whose_folder_is_a_self_symlink_is_retried(runs, capsys):
    """--retry-failed used to fail forever: the loop was never removed, so the writer could not make the folder."""
    _, bad, _ = runs
    rows = _rows(bad)
    rows.append({**rows[0], "status": "failed", "success": False, "error": "RuntimeError: boom", "files": None})
    _write_rows(bad, rows)
    episode = bad / "Lift" / "episode_0"
    shutil.rmtree(episode)
    episode.symlink_to(episode)
    code, _, err = _resume(bad, capsys, "--retry-failed")
    assert code == 0, err
    assert episode.is_dir() and not episode.is_symlink() and _rows(bad)[-1]["status"] == "ok"


# ---- old rows (no digests): the committed baseline ----------------------------------------------------------------

def test_legacy_rows_are_read_unverified_and_compare_says_so(tmp_path, capsys):
    """Rows made before digests were recorded (copies of the committed baseline as such rows hold them) are still
    read; compare says which were not verified."""
    legacy, copy = tmp_path / "legacy", tmp_path / "copy"
    for folder in (legacy, copy):
        shutil.copytree(BASELINE, folder)
        make_legacy(folder)
    run = load_run(legacy)
    assert run.status == "complete" and run.unverified == len(run.episodes) == 8
    assert cli.main(["compare", str(legacy), str(copy), "--no-frames", "--out", str(tmp_path / "cmp")]) == 0
    out = capsys.readouterr().out
    assert "compare: IDENTICAL" in out
    assert "Files read unverified (rows made before sizes and digests were recorded): reference-lift 8, " \
           "reference-lift 8 episodes." in out


def test_the_schema_refuses_a_malformed_digest_and_a_task_that_is_a_path():
    from harness.runfolder.schema import MalformedRunError, check_manifest, check_row

    row = _rows(BASELINE)[0]
    with pytest.raises(MalformedRunError, match=r"files\['attention.npz'\] must be"):
        check_row({**row, "files": {"attention.npz": {"size": 1, "sha256": "xyz"}}}, "r", 1)
    with pytest.raises(MalformedRunError, match=r"files names '../x.npz'"):
        check_row({**row, "files": {"../x.npz": {"size": 1, "sha256": "0" * 64}}}, "r", 1)
    with pytest.raises(MalformedRunError, match=r"task '\.\./Lift' is not a task name"):
        check_row({**row, "task": "../Lift"}, "r", 1)
    for climbing in ("libero_object/../../x", "libero_object/..", "/abs/Lift", "Lift/"):
        with pytest.raises(MalformedRunError, match=r"is not a task name"):
            check_row({**row, "task": climbing}, "r", 1)
    manifest = json.loads((BASELINE / "manifest.json").read_text())
    for bad in ("../../elsewhere", "libero_object/../../elsewhere"):
        manifest["protocol"]["tasks"] = [bad]
        with pytest.raises(MalformedRunError, match=r"not a task name"):
            check_manifest(manifest, "m")


def test_a_libero_task_name_nests_one_folder_inside_the_run():
    """LIBERO tasks are '<suite>/<index>': the schema takes plain names joined by '/', and no other path."""
    from harness.runfolder.schema import TASK_NAME

    assert TASK_NAME.match("libero_object/3") and TASK_NAME.match("Lift")
    assert not any(TASK_NAME.match(t) for t in ("../Lift", "a/../b", "a//b", ".hidden", "a/.x", "a\\b", ""))


# ---- a gate that cannot be emptied -------------------------------------------------------------------------------

def _two_task_copy(run: Path, dest: Path) -> Path:
    """`run` (Lift only) as a Lift + Stack run: Stack's episodes are Lift's files under Stack's folders, with rows
    and jobs to match (every reader accepts it: the digests are those of the copied files)."""
    shutil.copytree(run, dest)
    manifest = json.loads((dest / "manifest.json").read_text())
    manifest["protocol"]["tasks"] = ["Lift", "Stack"]
    manifest["jobs"] = manifest["jobs"] + [["Stack", k, s] for _, k, s in manifest["jobs"]]
    (dest / "manifest.json").write_text(json.dumps(manifest))
    rehash(dest)  # as a Lift + Stack run would have recorded it
    shutil.copytree(dest / "Lift", dest / "Stack")
    rows = _rows(dest)
    _write_rows(dest, rows + [{**r, "task": "Stack", "directory": r["directory"].replace("Lift", "Stack")} for r in rows])
    return dest


@pytest.mark.slow
def test_a_candidate_that_drops_a_task_is_incomplete_exit_4(made, tmp_path, capsys):
    baseline = _two_task_copy(made, tmp_path / "lift_stack")
    for fail_on in ("suspect", "regressed"):
        code = cli.main(["compare", str(baseline), str(made), "--no-frames", "--out", str(tmp_path / "cmp"),
                         "--fail-on", fail_on])
        out = capsys.readouterr().out
        assert code == 4 and "compare: INCOMPLETE" in out and "lacks 2 finished episode(s)" in out and "(Stack 2)" in out
    result = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert result["verdict"] == "INCOMPLETE" and result["exit_code"] == 4 and result["incomplete"]["tasks"] == {"Stack": 2}


@pytest.mark.slow
def test_a_candidate_missing_jobs_is_incomplete(runs, tmp_path, capsys):
    good, bad, _ = runs
    _write_rows(bad, _rows(bad)[:1])  # episode 1 never finished
    code = cli.main(["compare", str(good), str(bad), "--no-frames", "--out", str(tmp_path / "cmp")])
    assert code == 4 and "compare: INCOMPLETE" in capsys.readouterr().out
    # the other way round the candidate has more than the baseline: its extra episode is left out, not a failure
    assert cli.main(["compare", str(bad), str(good), "--no-frames", "--out", str(tmp_path / "cmp2")]) == 0


@pytest.mark.slow
def test_regress_whose_candidate_never_ran_a_task_is_incomplete(made, fixtures_dir, tmp_path):
    """An executor that loses a task's jobs (a lost worker, a node gone) must not leave the gate passing."""
    from harness.run.executor import SequentialExecutor
    from harness.gate.regress import exit_code, regress

    class LosesStack(SequentialExecutor):
        def run(self, jobs, on_step=None):
            return super().run([j for j in jobs if j.task != "Stack"], on_step)

    baseline = _two_task_copy(made, tmp_path / "lift_stack")
    result = regress(baseline, str(fixtures_dir / "tiny"), out=tmp_path / "out", run_name="cand", executor=LosesStack,
                     progress=False)
    assert result.verdict == "INCOMPLETE" and result.incomplete.tasks == {"Stack": 2}
    assert exit_code(result) == exit_code(result, "regressed") == 4


# ---- exit codes that lie -----------------------------------------------------------------------------------------

def _small_disk(path: Path, size: str):
    """A tmpfs of `size` at `path` (root only); None where it cannot be mounted."""
    import subprocess

    path.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    return path if mounted.returncode == 0 else None


def _unmount(path: Path) -> None:
    import subprocess

    subprocess.run(["umount", str(path)], check=True)


@pytest.mark.slow
def test_compare_with_its_output_on_a_full_disk_is_exit_2_not_regressed(runs, tmp_path, capsys, monkeypatch):
    good, bad, _ = runs
    disk = _small_disk(tmp_path / "full", "8k")
    if disk is None:  # not root: the same OSError, injected where compare writes compare.json
        import errno

        import harness.report.compare_html as compare_html

        def full(*args, **kwargs):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(compare_html, "atomic_write_json", full)
        disk = tmp_path / "full"
    try:
        _one_line_exit_2(["compare", str(good), str(bad), "--no-frames", "--out", str(disk / "cmp")], capsys,
                         "could not write compare's outputs", "No space left on device", "the verdict was IDENTICAL")
    finally:
        if disk.is_mount():
            _unmount(disk)


def test_an_array_file_cut_by_a_full_disk_leaves_no_zipfile_trace(tmp_path):
    """np.savez leaves its ZipFile open when the disk fills; its __del__ used to print a 7-line trace at exit."""
    import subprocess
    import sys

    disk = _small_disk(tmp_path / "full", "64k")
    if disk is None:
        pytest.skip("needs root to mount a small tmpfs")  # not counted: the CI container runs as root
    script = ("import numpy as np, gc\nfrom harness.files import write_atomic\n"
              f"try:\n    write_atomic({str(disk / 'a.npz')!r}, lambda f: np.savez(f, x=np.zeros(100000)))\n"
              "except OSError as e:\n    print('refused:', e.strerror)\ngc.collect()\n")
    try:
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=REPO, timeout=120)
    finally:
        _unmount(disk)
    assert done.stdout.strip() == "refused: No space left on device"
    assert done.stderr == "" and not list((tmp_path / "full").glob("*"))


# ---- bounds before anything heavy --------------------------------------------------------------------------------

def _run_refused(argv, capsys, tmp_path, *expected: str) -> None:
    """`run argv` is one line naming the bound, exit 2, and leaves no run folder behind."""
    out = tmp_path / "runs"
    _one_line_exit_2(["run", "--task", "Lift", "--out", str(out), *argv], capsys, *expected)
    assert not out.exists() or not any(out.iterdir())


BOUNDS = {
    "huge episodes": (["--episodes", "99999999999999999999"], ["episode jobs, more than one run holds (100000)"]),
    "jobs over the maximum": (["--task", "Stack", "--episodes", "60000"], ["120000 episode jobs", "at most 50000"]),
    "huge seed": (["--seed", "99999999999999999999"], ["outside the simulator's seed range 0..4294967295"]),
    "last seed over the range": (["--seed", "4294967295", "--episodes", "2"], ["choose --seed <= 4294967294"]),
    "huge camera": (["--camera", "image_primary=agentview:100000"], ["larger than 2048 px"]),
    "long run name": (["--run-name", "r" * 300], ["--run-name is 300 bytes long", "choose a shorter name"]),
    "huge max steps": (["--max-steps", "10000000"], ["--max-steps 10000000 is more than an episode may run"]),
    "episodes 1.5": (["--episodes", "1.5"], ["argument --episodes: invalid int value: '1.5'; pass a whole number"]),
    "episodes nan": (["--episodes", "nan"], ["argument --episodes: invalid int value: 'nan'"]),
    "max steps inf": (["--max-steps", "inf"], ["argument --max-steps: invalid int value: 'inf'"]),
}


@pytest.mark.parametrize("bound", sorted(BOUNDS))
def test_a_bound_is_one_line_before_anything_heavy(bound, capsys, tmp_path, fixtures_dir):
    argv, expected = BOUNDS[bound]
    _run_refused(["--model", str(fixtures_dir / "tiny"), *argv], capsys, tmp_path, *expected)


def test_argparse_errors_of_every_command_are_one_line(capsys):
    for argv, expected in ((["compare", "a"], "required: CANDIDATE_RUN"), (["replay"], "required: RUN_DIR"),
                           (["regress", "--model", "m", "--baseline", "b", "--max-episodes", "x"],
                            "--max-episodes: invalid int value"),
                           (["compare", "a", "b", "--fail-on", "never"], "invalid choice: 'never'")):
        with pytest.raises(SystemExit) as exit_info:
            cli.main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert exit_info.value.code == 2 and len(err) == 1 and expected in err[0] and "--help" in err[0], err


def _tiny_copy(fixtures_dir: Path, dest: Path, change) -> Path:
    shutil.copytree(fixtures_dir / "tiny", dest)
    config = json.loads((dest / "config.json").read_text())
    change(config["model"]["transformer_kwargs"])
    (dest / "config.json").write_text(json.dumps(config))
    return dest


def test_a_config_with_a_word_for_a_number_is_one_line_naming_the_field(fixtures_dir, tmp_path, capsys):
    model = _tiny_copy(fixtures_dir, tmp_path / "two", lambda tk: tk.update(num_layers="two"))
    _run_refused(["--model", str(model)], capsys, tmp_path,
                 "config.json model.transformer_kwargs.num_layers must be a positive whole number, got 'two'")


def test_a_checkpoint_too_big_for_the_machine_is_refused_before_initialising(fixtures_dir, tmp_path, capsys):
    from harness.octo.config import OctoConfig, parameter_estimate
    from harness.octo.loading import check_memory

    model = _tiny_copy(fixtures_dir, tmp_path / "huge", lambda tk: tk.update(num_layers=10000, mlp_dim=5e7))
    config = OctoConfig.from_json(model / "config.json")
    assert parameter_estimate(config) > 10000 * 2 * config.token_embedding_size * 50_000_000
    _run_refused(["--model", str(model)], capsys, tmp_path, "GiB of parameters (10000 layers, mlp_dim 50000000",
                 "this machine has")
    tiny = OctoConfig.from_json(fixtures_dir / "tiny" / "config.json")
    check_memory(tiny, "tiny", available=4 * parameter_estimate(tiny))  # exactly enough passes
    with pytest.raises(ValueError, match="GiB of parameters"):
        check_memory(tiny, "tiny", available=4 * parameter_estimate(tiny) - 1)


def test_k_larger_than_the_cameras_patch_grid_is_refused(fixtures_dir, tmp_path, capsys):
    _run_refused(["--model", str(fixtures_dir / "tiny"), "--intervene", "mask-top:99999:attention"], capsys, tmp_path,
                 "K=99999 is more than the", "choose K <=")


# ---- compare says what differs -----------------------------------------------------------------------------------

@pytest.mark.slow
def test_compare_of_an_intervention_run_names_the_intervention_not_the_model(made, fixtures_dir, tmp_path, capsys):
    manifest = json.loads((made / "manifest.json").read_text())
    protocol = Protocol.from_dict(manifest["protocol"]).replace(model_fingerprint=None)
    intervened = protocol.replace(policy=protocol.policy.__class__(**{**vars(protocol.policy),
                                                                      "intervention": "mask-all"}))
    execute(intervened, tmp_path, "masked", progress=False)
    code = cli.main(["compare", str(made), str(tmp_path / "masked"), "--no-frames", "--out", str(tmp_path / "cmp"),
                     "--fail-on", "regressed"])
    out = capsys.readouterr().out
    assert code == 0
    assert "the model change alone" not in out and "any difference is the candidate's" not in out
    assert "**Step-0 drift** (same seed and scene; the arms differ in policy.intervention (none -> mask-all), not in " \
           "the model" in out
    result = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert result["differs"]["model"] is False and [o["field"] for o in result["differs"]["other"]] == ["policy.intervention"]
    assert "not the model's alone (the protocols differ in policy.intervention" in result["provenance"]["summary"]
    html = (tmp_path / "cmp" / "compare.html").read_text()
    assert "differ in policy.intervention (none -&gt; mask-all), not in the model" in html


def test_what_differs_separates_the_model_from_other_settings():
    from harness.analysis.compare import what_differs

    base = {"model": "/m/a", "model_fingerprint": "sha256:1", "tasks": ["Lift"], "policy": {"intervention": None,
                                                                                           "inference_batch": 1}}
    model_only = what_differs(base, {**base, "model": "/m/b", "model_fingerprint": "sha256:2"})
    assert model_only["model"] and not model_only["other"] and model_only["drift_label"].endswith("the model change alone")
    both = what_differs(base, {**base, "model": "/m/b", "policy": {"intervention": "mask-all@image_wrist",
                                                                   "inference_batch": 1}})
    assert both["model"] and "the model and in policy.intervention (none -> mask-all@image_wrist)" in both["drift_label"]
    neutral = what_differs(base, {**base, "tasks": ["Lift", "Stack"], "policy": {"intervention": None,
                                                                                  "inference_batch": 8}})
    assert not neutral["model"] and not neutral["other"] and "float noise" in neutral["drift_label"]

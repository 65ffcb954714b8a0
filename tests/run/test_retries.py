"""Infrastructure failures and episode failures (issue 66): which exceptions are which, the retry rule over any
executor (`Retrying`), and how a run folder records, counts and resumes them. The executors' own losses (a killed
worker, a lost Ray node, a killed LIBERO server) are tested end to end in test_parallel.py, test_ray_executor.py and
tests/libero/test_libero_env.py."""

from __future__ import annotations

import json

import pytest

from harness.run.executor import InfrastructureError, Retrying, failure_of
from harness.run.jobs import EpisodeJob
from harness.run.store import EpisodeRow, RunStore, recovery, recovery_lines, statistics
from harness.run.workers import PolicyError, WorkerDied

JOBS = [EpisodeJob("Lift", k, 10 + k) for k in range(3)]


def _ok(job: EpisodeJob) -> EpisodeRow:
    return EpisodeRow(run="r", task=job.task, episode=job.episode, seed=job.seed, status="ok", success=True, steps=8,
                      total_return=1.0, seconds_per_step=0.1, simulation_per_step=0.05, inference_per_step=0.04,
                      overhead_fraction=0.1, directory=job.directory)


def _lost(job: EpisodeJob, step: int, lost: str = "worker") -> EpisodeRow:
    return EpisodeRow.failed("r", job, f"WorkerDied: {lost} gone", steps=step, failure="infrastructure", lost=lost)


class Scripted:
    """An executor whose rows follow a script: {job key: [row maker per attempt]} (the jobs it was given, logged)."""

    def __init__(self, script):
        self.script = {k: list(v) for k, v in script.items()}
        self.calls: list[list[EpisodeJob]] = []

    def run(self, jobs, on_step=None):
        self.calls.append(list(jobs))
        for job in jobs:
            yield self.script[job.key].pop(0)(job)

    def close(self):
        pass


def _retrying(script, tmp_path, retries=2):
    executor = Scripted(script)
    return executor, list(Retrying(executor, retries, tmp_path).run(JOBS))


def test_a_lost_job_runs_again_from_an_empty_folder_and_its_row_lists_the_lost_attempt(tmp_path):
    folder = tmp_path / JOBS[1].directory
    folder.mkdir(parents=True)
    (folder / "episode.json").write_text("{}")  # what the lost attempt left
    executor, rows = _retrying({JOBS[0].key: [_ok], JOBS[1].key: [lambda j: _lost(j, 5, "node"), _ok],
                                JOBS[2].key: [_ok]}, tmp_path)
    assert executor.calls == [JOBS, [JOBS[1]]]  # the retry after the others, on whichever worker is free
    assert not folder.exists()
    assert [r.status for r in rows] == ["ok"] * 3
    (retried,) = [r for r in rows if r.retries]
    assert retried.key == JOBS[1].key and retried.retries == ({"lost": "node", "cause": "WorkerDied: node gone", "step": 5},)
    assert recovery_lines(recovery(rows)) == ["1 episode retried after a lost node"]


def test_an_episode_failure_is_never_retried(tmp_path):
    def policy_failed(job):
        return EpisodeRow.failed("r", job, "PolicyError: FloatingPointError: injected", steps=3)

    executor, rows = _retrying({JOBS[0].key: [policy_failed], JOBS[1].key: [_ok], JOBS[2].key: [_ok]}, tmp_path)
    assert executor.calls == [JOBS]
    assert rows[0].failure == "episode" and not rows[0].retries and recovery(rows) is None


def test_a_loss_at_the_same_step_again_is_the_episode_s_own_failure(tmp_path):
    executor, rows = _retrying({JOBS[0].key: [lambda j: _lost(j, 6), lambda j: _lost(j, 6)], JOBS[1].key: [_ok],
                                JOBS[2].key: [_ok]}, tmp_path)
    (row,) = [r for r in rows if r.key == JOBS[0].key]
    assert row.status == "failed" and row.failure == "episode" and row.lost is None
    assert "again at step 6 on a retry" in row.error and len(row.retries) == 1
    stats = statistics(rows, ["Lift"])["overall"]
    assert stats["failed"] == 1 and stats["n"] == 2  # an episode failure stays in the failed count


def test_after_n_retries_the_job_is_an_infrastructure_failure_outside_the_statistics(tmp_path):
    executor, rows = _retrying({JOBS[0].key: [lambda j: _lost(j, 1), lambda j: _lost(j, 2), lambda j: _lost(j, 3)],
                                JOBS[1].key: [_ok], JOBS[2].key: [_ok]}, tmp_path)
    assert len(executor.calls) == 3
    (row,) = [r for r in rows if r.key == JOBS[0].key]
    assert row.lost_infrastructure and [a["step"] for a in row.retries] == [1, 2]
    stats = statistics(rows, ["Lift"])["overall"]
    assert stats["n"] == 2 and stats["failed"] == 0
    summary = recovery(rows)
    assert summary == {"episodes_retried": 1, "attempts_lost": 2, "retried_after": {"worker": 1}, "lost": ["Lift/episode_0"]}
    assert "run --resume" in recovery_lines(summary)[-1] and "Lift/episode_0" in recovery_lines(summary)[-1]
    _, none = _retrying({JOBS[0].key: [lambda j: _lost(j, 1)], JOBS[1].key: [_ok], JOBS[2].key: [_ok]}, tmp_path, 0)
    assert none[0].lost_infrastructure and not none[0].retries  # --retries 0: never retried


def test_a_row_round_trips_its_failure_kind_and_retries_and_an_ok_row_keeps_its_keys(tmp_path):
    row = _lost(JOBS[0], 4)
    retried = EpisodeRow.from_dict(json.loads(json.dumps({**_ok(JOBS[1]).to_dict(),
                                                          "retries": [{"lost": "node", "cause": "x", "step": 2}]})))
    assert EpisodeRow.from_dict(row.to_dict()) == row
    assert retried.retries == ({"lost": "node", "cause": "x", "step": 2},)
    assert not {"failure", "lost", "retries"} & set(_ok(JOBS[0]).to_dict())  # the files of runs that lost nothing
    store = RunStore(tmp_path / "run")
    store.dir.mkdir()
    for r in (row, retried):
        store.append(r)
    assert store.load_rows() == {row.key: row, retried.key: retried}


@pytest.mark.parametrize("exc, expected", [
    (WorkerDied("worker process died: signal 9 (SIGKILL)"), ("infrastructure", "worker")),
    (InfrastructureError("policy replica lost: ...", "policy replica"), ("infrastructure", "policy replica")),
    (PolicyError("FloatingPointError: injected"), ("episode", None)),
    (ValueError("the action is not finite"), ("episode", None)),
])
def test_failure_kinds(exc, expected):
    assert failure_of(exc) == expected


def test_a_libero_server_lost_is_infrastructure_and_one_that_reports_an_error_is_the_episode_s():
    from envs.libero_env import LiberoServerError, LiberoServerLost

    assert failure_of(LiberoServerLost("the LIBERO server died during 'step' (signal 9 (SIGKILL))")) == \
        ("infrastructure", "LIBERO server")
    assert failure_of(LiberoServerError("LIBERO step: MujocoException: unstable simulation")) == ("episode", None)


def test_a_lost_gl_context_is_infrastructure():
    error = type("GLError", (RuntimeError,), {"__module__": "OpenGL.error"})
    assert failure_of(error("EGL_CONTEXT_LOST")) == ("infrastructure", "render context")


def test_a_resume_runs_an_infrastructure_failure_again_without_retry_failed(tmp_path):
    store = RunStore(tmp_path)
    rows = {JOBS[0].key: _lost(JOBS[0], 2), JOBS[1].key: EpisodeRow.failed("r", JOBS[1], "PolicyError: x")}
    assert store.standing_jobs(rows, retry_failed=False) == {JOBS[1].key}  # the episode failure stands
    assert store.standing_jobs(rows, retry_failed=True) == set()


def test_a_negative_retry_count_is_one_line_before_anything_loads(fixtures_dir, tmp_path, capsys):
    from harness import cli

    code = cli.main(["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--out", str(tmp_path),
                     "--retries", "-1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--retries" in err[0]
    assert not any(tmp_path.iterdir())

"""The run folder on disk: lock, manifest, the results.jsonl record, derived tables, and clean-up for resume.

Layout (the interface every reader builds on; see README "The run folder"):

  <out>/<run>/.lock           fcntl lock held by the writing process; holds its pid
  <out>/<run>/manifest.json   written at the start: format, run, created, protocol, protocol_hash, jobs, model, ...;
                              rewritten only to add what was lost and retried ("recovery", outside the protocol)
  <out>/<run>/results.jsonl   SOURCE OF TRUTH: one line per finished episode, appended and fsynced (last line of a job wins)
  <out>/<run>/results.json    derived, rewritten atomically after each episode: manifest, status, episodes, missing, statistics
  <out>/<run>/summary.csv     derived: one row per episode (+ its task's success statistics)
  <out>/<run>/statistics.csv  derived: one row per task and one "overall" row (n, successes, rate, interval)
  <out>/<run>/<task>/episode_<k>/...   episode outputs (harness/outputs/writers.py); episode.json written last

Only the process holding the lock writes here; executors write only inside the episode folders of their jobs.
A lock left by a dead process does not block: the kernel releases flock locks when their holder dies.
"""

from __future__ import annotations

import csv
import errno
import fcntl
import io
import json
import logging
import os
import re
import shutil
from dataclasses import dataclass, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable

from harness.measures.stats import success_summary
from harness.bounded import MAX_JSONL_BYTES, BoundsError, read_bytes, read_json
from harness.files import atomic_write_json, json_safe, write_atomic
from harness.run.jobs import FORMAT, EpisodeJob
from harness.runfolder.integrity import LEGACY_RESUME, check_run_files, episode_problem
from harness.runfolder.schema import MalformedRunError, check_manifest, check_row, parse_row

log = logging.getLogger(__name__)

LOCK = ".lock"
MANIFEST = "manifest.json"
RESULTS_JSONL = "results.jsonl"
RESULTS_JSON = "results.json"
SUMMARY_CSV = "summary.csv"
STATISTICS_CSV = "statistics.csv"
_EPISODE_DIR = re.compile(r"^episode_(\d+)$")


class RunLockedError(RuntimeError):
    """Another live process writes into this run folder."""


class ResultsWriteError(RuntimeError):
    """results.jsonl could not be appended: the run must stop (message: one line, path and OS error)."""


@dataclass(frozen=True)
class EpisodeRow:
    """One finished episode, as results.jsonl holds it (`to_dict`: "return" for `total_return`)."""

    run: str
    task: str
    episode: int
    seed: int
    status: str  # "ok" | "failed"
    success: bool
    steps: int
    total_return: float | None
    seconds_per_step: float | None  # None for failed episodes
    simulation_per_step: float | None
    inference_per_step: float | None
    overhead_fraction: float | None  # (step - simulation - inference) / step
    directory: str  # relative to the run folder: "<task>/episode_<k>"
    error: str | None = None
    platform: str | None = None  # platform_fingerprint of the driver that recorded it (harness/runfolder/platform.py)
    files: dict | None = None  # {name: {"size", "sha256"}} of the episode's data files (harness/runfolder/integrity.py)
    furthest_phase: str | None = None  # the furthest task phase the episode reached (envs.phases); left out when None
    # a failed row's kind (schema.FAILURE_KINDS): "episode" (the policy, the env, the physics: kept in the statistics' failed
    # count) or "infrastructure" (what ran it was lost: run again by a resume); left out when None (ok rows, older runs)
    failure: str | None = None
    lost: str | None = None  # an infrastructure failure's lost part ("worker", "node", "LIBERO server", ...)
    # the attempts lost before this one, oldest first: [{"lost", "cause" (one line), "step"}]; left out when none
    retries: tuple = ()

    @property
    def key(self) -> tuple[str, int]:
        return (self.task, self.episode)

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["return"] = d.pop("total_return")
        for name in SPARSE_FIELDS:  # rows without them (and those of older runs) keep their keys
            if not d[name]:
                del d[name]
        if "retries" in d:
            d["retries"] = [dict(r) for r in d["retries"]]
        return json_safe(d)

    @classmethod
    def from_dict(cls, data: dict) -> "EpisodeRow":
        d = dict(data)
        d["total_return"] = d.pop("return", None)
        names = {f.name for f in fields(cls)}
        if d.get("retries") is not None:
            d["retries"] = tuple(d["retries"])
        return cls(**{k: v for k, v in d.items() if k in names})

    @classmethod
    def failed(cls, run: str, job: EpisodeJob, error: str, steps: int = 0, failure: str = "episode",
               lost: str | None = None) -> "EpisodeRow":
        return cls(run=run, task=job.task, episode=job.episode, seed=job.seed, status="failed", success=False,
                   steps=steps, total_return=None, seconds_per_step=None, simulation_per_step=None,
                   inference_per_step=None, overhead_fraction=None, directory=job.directory, error=error,
                   failure=failure, lost=lost)

    @property
    def lost_infrastructure(self) -> bool:
        """Failed because what ran it was lost (after its retries): outside the statistics, run again on resume."""
        return self.status == "failed" and self.failure == "infrastructure"


SPARSE_FIELDS = ("furthest_phase", "failure", "lost", "retries")  # results.jsonl holds them only when set


CSV_COLUMNS = ["run", "task", "episode", "seed", "status", "success", "steps", "return", "seconds_per_step",
               "simulation_per_step", "inference_per_step", "overhead_fraction", "directory", "error", "platform"]
STAT_COLUMNS = ["n", "successes", "failed", "success_rate", "ci_low", "ci_high", "method", "confidence"]


def statistics(rows: Iterable[EpisodeRow], tasks: Iterable[str], method: str = "wilson", confidence: float = 0.95) -> dict:
    """{"tasks": {task: summary}, "overall": summary}: success statistics over the episodes that ran ("ok");
    episodes that failed with an error are counted in "failed", not in n; jobs lost to the infrastructure after their
    retries are in neither (`recovery` names them)."""
    rows = list(rows)

    def summary(subset: list[EpisodeRow]) -> dict:
        ok = [r for r in subset if r.status == "ok"]
        out = success_summary(sum(bool(r.success) for r in ok), len(ok), method=method, confidence=confidence)
        out["failed"] = sum(r.status != "ok" and not r.lost_infrastructure for r in subset)
        return out

    return {"tasks": {t: summary([r for r in rows if r.task == t]) for t in tasks}, "overall": summary(rows)}


def recovery(rows: Iterable[EpisodeRow]) -> dict | None:
    """What a run lost to its infrastructure and won back (None when nothing was lost): {"episodes_retried",
    "attempts_lost" (summed over them), "retried_after": {lost part: episodes}, "lost": [job folders failed as
    infrastructure after their retries]}. An episode counts under the part lost at its last lost attempt."""
    rows = list(rows)
    retried = [r for r in rows if r.retries]
    lost = [r.directory for r in rows if r.lost_infrastructure]
    if not retried and not lost:
        return None
    after: dict[str, int] = {}
    for r in retried:
        after[r.retries[-1]["lost"]] = after.get(r.retries[-1]["lost"], 0) + 1
    return {"episodes_retried": len(retried), "attempts_lost": sum(len(r.retries) for r in retried),
            "retried_after": after, "lost": lost}


def recovery_lines(summary: dict | None) -> list[str]:
    """The console's lines for `recovery(rows)`: "2 episodes retried after a lost worker", the jobs still lost."""
    if not summary:
        return []
    lines = [f"{n} episode{'s' if n != 1 else ''} retried after a lost {part}"
             for part, n in summary["retried_after"].items()]
    if summary["lost"]:
        lines.append(f"{len(summary['lost'])} lost to the infrastructure after their retries, not in the statistics "
                     f"(`run --resume` runs them again): {', '.join(summary['lost'])}")
    return lines


class RunStore:
    """One run folder. Use `with store.locked():` around everything that writes into it."""

    def __init__(self, run_dir: str | os.PathLike):
        self.dir = Path(run_dir)
        self.name = self.dir.name
        self._lock_fd: int | None = None

    # ---- lock ------------------------------------------------------------------------------------

    def lock(self) -> None:
        """Take the folder's lock (creating the folder) or raise RunLockedError naming the holder's pid."""
        self.dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.dir / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise RunLockedError(f"run folder {self.dir} is in use by process {holder}; wait for it to finish, "
                                     "or choose another --run-name") from None
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._lock_fd = fd

    def unlock(self) -> None:
        if self._lock_fd is not None:
            fd, self._lock_fd = self._lock_fd, None
            try:
                os.ftruncate(fd, 0)
            except OSError:
                pass
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    def __enter__(self) -> "RunStore":
        self.lock()
        return self

    def __exit__(self, *exc) -> None:
        self.unlock()

    # ---- manifest --------------------------------------------------------------------------------

    def read_manifest(self) -> dict | None:
        path = self.dir / MANIFEST
        check_run_files(self.dir, (MANIFEST, RESULTS_JSONL))  # a link out of the folder or a loop: one line, exit 2
        if not path.is_file():
            return None
        try:
            manifest = read_json(path)
        except BoundsError:
            raise
        except (OSError, ValueError) as e:
            raise ValueError(f"{path} is unreadable ({e}); use --overwrite to start the run afresh") from None
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            found = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
            raise ValueError(f"{path} is not an {FORMAT} manifest (format {found!r}); "
                             "use --overwrite or another --run-name")
        return check_manifest(manifest, path)

    def foreign_content(self, tasks: Iterable[str] = ()) -> list[str]:
        """Names in a folder without manifest that a run would not write (guards --run-name against a wrong folder)."""
        ours = {LOCK, MANIFEST, RESULTS_JSONL, RESULTS_JSON, SUMMARY_CSV, STATISTICS_CSV,
                *(t.split("/")[0] for t in tasks)}  # a LIBERO task "libero_object/3" lives in libero_object/3/
        if not self.dir.is_dir() or (self.dir / MANIFEST).exists():
            return []
        return sorted(p.name for p in self.dir.iterdir() if p.name not in ours and ".tmp." not in p.name)

    def write_manifest(self, manifest: dict) -> None:
        atomic_write_json(self.dir / MANIFEST, manifest)

    def clear(self) -> None:
        """--overwrite: delete everything in the folder but the lock."""
        for path in self.dir.iterdir():
            if path.name == LOCK:
                continue
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()

    # ---- results ---------------------------------------------------------------------------------

    def load_rows(self, jobs: set[tuple[str, int]] | dict[tuple[str, int], int] | None = None
                  ) -> dict[tuple[str, int], EpisodeRow]:
        """Rows of results.jsonl by job (last line wins). A torn last line (killed mid-append) is cut off; any other
        malformed line, or a row of a job not in `jobs` (when given), is a MalformedRunError."""
        path = self.dir / RESULTS_JSONL
        check_run_files(self.dir, (RESULTS_JSONL,))
        if not path.is_file():
            return {}
        data = read_bytes(path, MAX_JSONL_BYTES, "JSON-lines file")
        if data and not data.endswith(b"\n"):
            keep = data.rfind(b"\n") + 1
            with open(path, "r+b") as f:
                f.truncate(keep)
                f.flush()
                os.fsync(f.fileno())
            data = data[:keep]
        rows: dict[tuple[str, int], EpisodeRow] = {}
        for number, line in enumerate(data.decode(errors="replace").splitlines(), 1):
            if line.strip():
                row = EpisodeRow.from_dict(check_row(parse_row(line, path, number), path, number, jobs))
                rows[row.key] = row
        return rows

    def append(self, row: EpisodeRow) -> None:
        """Append one row to results.jsonl and fsync; ResultsWriteError (one line) when that fails."""
        path = self.dir / RESULTS_JSONL
        line = (json.dumps(row.to_dict(), sort_keys=True) + "\n").encode()
        try:
            fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                written = os.write(fd, line)
                if written != len(line):
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError as e:
            raise ResultsWriteError(f"cannot append to {path}: {e.strerror or e} (errno {e.errno}); "
                                    "free space or fix permissions, then run the same command again to resume") from None

    def standing_jobs(self, rows: dict, retry_failed: bool, manifest: dict | None = None) -> set[tuple[str, int]]:
        """Jobs whose rows stand (a resume skips them): failed ones (unless retried; an infrastructure failure never
        stands) and finished ones whose folder holds the files its row records, unchanged
        (harness/runfolder/integrity.py). A finished episode whose files are missing or damaged, or whose folder is
        a symlink or leads out of the run, is said on stderr and run again (its folder is removed as an incomplete
        one: a symlink as a link, never followed)."""
        done = set()
        for key, row in rows.items():
            if row.status != "ok":
                if not retry_failed and not row.lost_infrastructure:
                    done.add(key)
                continue
            directory = f"{row.task}/episode_{row.episode}"
            try:
                problem = episode_problem(self.dir, directory, row.to_dict(), f"{self.dir / RESULTS_JSONL}",
                                          legacy=LEGACY_RESUME, manifest=manifest)
            except MalformedRunError as exc:  # leads out of the run folder or loops: the run's own folder is rewritten
                problem = str(exc).split("; ")[0]
            if problem is None:
                done.add(key)
            else:
                log.warning("%s; running episode %s again", problem, directory)
        return done

    def record_recovery(self, manifest: dict, rows: dict, retries: int, default: int) -> None:
        """The manifest's "recovery" (outside the protocol and its hash): the retries allowed and what was lost and
        won back (`recovery`), rewritten when that changes; absent while nothing was lost and `retries` is the
        `default`."""
        lost = recovery(rows.values())
        if lost is None and retries == default:
            if "recovery" in manifest:  # what was lost has run again (a resume): no stale record stays
                del manifest["recovery"]
                self.write_manifest(manifest)
            return
        record = {"retries": retries, **(lost or {})}
        if manifest.get("recovery") != record:
            manifest["recovery"] = record
            self.write_manifest(manifest)

    def rewrite_rows(self, rows: Iterable[EpisodeRow]) -> None:
        """Replace results.jsonl by `rows` in one atomic rename (a renamed run's rows take its new name)."""
        data = "".join(json.dumps(row.to_dict(), sort_keys=True) + "\n" for row in rows).encode()
        write_atomic(self.dir / RESULTS_JSONL, lambda f: f.write(data))

    def write_derived(self, manifest: dict, jobs: list[EpisodeJob], rows: dict[tuple[str, int], EpisodeRow],
                      status: str, method: str = "wilson") -> None:
        """results.json, summary.csv and statistics.csv from the rows (atomic; rows sorted by job order)."""
        ordered = [rows[j.key] for j in jobs if j.key in rows]
        tasks = list(dict.fromkeys(j.task for j in jobs))
        stats = statistics(ordered, tasks, method=method)
        recovered = recovery(ordered)
        atomic_write_json(self.dir / RESULTS_JSON, {
            "manifest": manifest, "status": status, "episodes": [r.to_dict() for r in ordered],
            "missing": len(jobs) - len(ordered), "statistics": stats,
            **({"recovery": recovered} if recovered else {}),  # left out when nothing was lost
        })
        by_task = stats["tasks"]
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(CSV_COLUMNS + ["task_success_rate", "task_ci_low", "task_ci_high", "ci_method"])
        for r in ordered:
            d, t = r.to_dict(), by_task[r.task]
            writer.writerow([_cell(d[c]) for c in CSV_COLUMNS]
                            + [_cell(json_safe(t[c])) for c in ("success_rate", "ci_low", "ci_high")] + [t["method"]])
        write_atomic(self.dir / SUMMARY_CSV, lambda f: f.write(buffer.getvalue().encode()))
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(["run", "task"] + STAT_COLUMNS)
        for task, s in [*by_task.items(), ("overall", stats["overall"])]:
            writer.writerow([self.name, task] + [_cell(json_safe(s[c])) for c in STAT_COLUMNS])
        write_atomic(self.dir / STATISTICS_CSV, lambda f: f.write(buffer.getvalue().encode()))

    # ---- clean-up --------------------------------------------------------------------------------

    def remove_temporaries(self) -> list[Path]:
        """Delete `*.tmp.*` files anywhere in the folder (leftovers of killed processes). Returns what was deleted."""
        removed = []
        for path in self.dir.rglob("*.tmp.*"):
            if path.is_file():
                path.unlink(missing_ok=True)
                removed.append(path)
        return removed

    def remove_incomplete(self, tasks: Iterable[str], keep: set[tuple[str, int]]) -> list[Path]:
        """Delete every `<task>/episode_<k>` folder whose job is not in `keep` (not finished, or to be rerun). A
        symlink in their place (the run never writes one; a loop, or a link out of the folder) is removed as a
        link, never followed; so is a task folder that is a symlink (its episodes are then not kept: see the
        driver)."""
        removed = []
        for task in tasks:
            task_dir = self.dir / task
            if task_dir.is_symlink():
                task_dir.unlink()
                removed.append(task_dir)
                continue
            if not task_dir.is_dir():
                continue
            for path in task_dir.iterdir():
                match = _EPISODE_DIR.match(path.name)
                if not match or (task, int(match.group(1))) in keep:
                    continue
                if path.is_symlink() or not path.is_dir():  # a link, or a plain file where the episode's folder
                    path.unlink()                          # belongs: removed (never followed), the episode runs again
                else:
                    shutil.rmtree(path)
                removed.append(path)
        return removed


def _cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, float) and value != value:
        return ""
    return value


def now_utc() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")

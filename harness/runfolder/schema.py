"""The one check of what a run folder's files hold, shared by run, resume, report, compare, regress and replay.

`check_manifest(data, path)` and `check_row(data, path, line)` take parsed JSON and raise `MalformedRunError`
(a ValueError: the command line prints one line and exits 2) naming the file, the field and the fix, instead
of letting a wrong type surface later as a traceback (exit 1, which for compare and regress means
"regression"). They check types and the consistency a reader relies on (jobs are (task, episode, seed)
triples of the protocol's tasks; a row's job is one of the manifest's jobs), not values a newer harness may
add: unknown keys pass. What the files on disk hold against what the rows record (confinement, digests) is
checked by harness/runfolder/integrity.py, called by the same readers.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Any, Mapping

from harness.bounded import MAX_JSON_BYTES, BoundsError, loads_json, read_json, short

FIX = "repair the file or re-create the run (octo-harness run ... --overwrite)"
ROW_STATUSES = ("ok", "failed")
FAILURE_KINDS = ("episode", "infrastructure")  # a failed row's kind (harness.run.executor.failure_of)
FILE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
# a task name: plain names joined by "/" (LIBERO tasks are "<suite>/<index>", their folders nest); no segment starts
# with "." so no ".." can climb out of the run
TASK_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*(/[A-Za-z0-9_][A-Za-z0-9_.-]*)*$")
SHA256 = re.compile(r"^[0-9a-f]{64}$")


class MalformedRunError(ValueError):
    """A run folder's manifest.json or results.jsonl holds something of the wrong type (one line, with the fix)."""


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _fail(path: Path | str, what: str) -> MalformedRunError:
    return MalformedRunError(f"{path}: {what}; {FIX}")


def _expect(path, name: str, value: Any, kinds: tuple, label: str, optional: bool = False) -> None:
    if value is None and optional:
        return
    ok = (_is_int(value) if kinds == (int,) else isinstance(value, kinds))
    if not ok:
        raise _fail(path, f"{name} must be {label}, got {type(value).__name__} {_short(value)}")


def _short(value: Any) -> str:
    return short(value, 40)


def protocol_hash(protocol: Mapping[str, Any]) -> str:
    """sha256 (hex) of the canonical JSON of a protocol dict: what a manifest's `protocol_hash` records."""
    from harness.files import json_safe

    return hashlib.sha256(json.dumps(json_safe(protocol), sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def expected_jobs(protocol: Mapping[str, Any]) -> list[list]:
    """The jobs a protocol implies: [task, k, seed + k] for each task, k = 0..episodes-1 (as Protocol.jobs())."""
    return [[task, k, protocol["seed"] + k] for task in protocol["tasks"] for k in range(protocol["episodes"])]


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """Nested mappings -> {"a.b.c": leaf} (an empty mapping is a leaf)."""
    if isinstance(data, Mapping) and data:
        out: dict[str, Any] = {}
        for key, value in data.items():
            out.update(flatten(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: data}


def _edited_fields(protocol: Mapping[str, Any], path: Path | str) -> list[str]:
    """Fields of `protocol` that differ from the copy the run's derived results.json holds (to name what was edited
    by hand); [] when there is no such copy."""
    copy_path = Path(path).with_name("results.json")
    try:
        copy = read_json(copy_path, MAX_JSON_BYTES)["manifest"]["protocol"]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    if not isinstance(copy, Mapping):
        return []
    a, b = flatten(dict(copy)), flatten(dict(protocol))
    return sorted(k for k in set(a) | set(b) if a.get(k, ...) != b.get(k, ...))


def check_protocol(protocol: Any, path: Path | str) -> dict:
    """The manifest's "protocol" block: types of the fields every reader uses."""
    _expect(path, "protocol", protocol, (dict,), "an object")
    _expect(path, "protocol.model", protocol.get("model"), (str,), "a model source string", optional=True)
    tasks = protocol.get("tasks")
    if not isinstance(tasks, list) or not tasks or not all(isinstance(t, str) and t for t in tasks):
        raise _fail(path, f"protocol.tasks must be a non-empty list of task names, got {_short(tasks)}")
    for task in tasks:
        if not TASK_NAME.match(task):
            raise _fail(path, f"protocol.tasks holds {_short(task)}, not a task name (a task's folder lies inside the run)")
    for name in ("episodes", "seed"):
        _expect(path, f"protocol.{name}", protocol.get(name), (int,), "an integer")
    if protocol["episodes"] < 1 or protocol["seed"] < 0:
        raise _fail(path, f"protocol.episodes must be >= 1 and protocol.seed >= 0, got {protocol['episodes']} "
                          f"and {protocol['seed']}")
    _expect(path, "protocol.max_steps", protocol.get("max_steps"), (int,), "an integer or null", optional=True)
    for name in ("env", "policy", "outputs"):
        _expect(path, f"protocol.{name}", protocol.get(name), (dict,), "an object", optional=True)
    _expect(path, "protocol.perturb", protocol.get("perturb"), (str,), "a perturbation string (KIND:LEVEL,...)",
            optional=True)
    for name in ("model_fingerprint", "instruction", "goal_images", "goal_fingerprint", "harness_version"):
        _expect(path, f"protocol.{name}", protocol.get(name), (str,), "a string or null", optional=True)
    return protocol


def check_manifest(manifest: Any, path: Path | str) -> dict:
    """A run-store manifest (format octo-harness-run/1): returns it unchanged or raises MalformedRunError."""
    _expect(path, "the manifest", manifest, (dict,), "a JSON object")
    _expect(path, "run", manifest.get("run"), (str,), "the run's name", optional=True)
    protocol = manifest.get("protocol")
    if protocol is not None:
        check_protocol(protocol, path)
    jobs = manifest.get("jobs")
    if not isinstance(jobs, list) or not jobs:
        raise _fail(path, f"jobs must be a non-empty list of [task, episode, seed], got {_short(jobs)}")
    tasks = set(protocol["tasks"]) if protocol is not None else None
    seen = set()
    for job in jobs:
        if not (isinstance(job, list) and len(job) == 3 and isinstance(job[0], str) and TASK_NAME.match(job[0])
                and _is_int(job[1]) and job[1] >= 0
                and (job[2] is None or _is_int(job[2]))):
            raise _fail(path, f"every job must be [task, episode >= 0, seed], got {_short(job)}")
        if tasks is not None and job[0] not in tasks:
            raise _fail(path, f"job {_short(job)} names a task that protocol.tasks does not hold")
        if (job[0], job[1]) in seen:
            raise _fail(path, f"job {_short(job)} appears twice")
        seen.add((job[0], job[1]))
    if protocol is not None and len(jobs) != len(protocol["tasks"]) * protocol["episodes"]:
        raise _fail(path, f"jobs holds {len(jobs)} episodes but protocol asks for {len(protocol['tasks'])} tasks x "
                          f"{protocol['episodes']} episodes")
    if protocol is not None:
        check_protocol_hash(manifest, path)
        for index, (job, implied) in enumerate(zip(jobs, expected_jobs(protocol))):
            if job != implied:
                raise _fail(path, f"jobs[{index}] is {_short(job)} but the protocol (tasks, episodes, seed) implies "
                                  f"{_short(implied)}: the manifest was edited by hand")
    for name in ("model", "platform", "versions", "statistics"):
        _expect(path, name, manifest.get(name), (dict,), "an object", optional=True)
    method = (manifest.get("statistics") or {}).get("ci_method")
    if method is not None and method not in ("wilson", "clopper-pearson"):
        raise _fail(path, f"statistics.ci_method must be wilson or clopper-pearson, got {_short(method)}")
    _expect(path, "platform_fingerprint", manifest.get("platform_fingerprint"), (str,), "a string", optional=True)
    return manifest


def check_protocol_hash(manifest: dict, path: Path | str) -> None:
    """The stored protocol_hash against the hash of the protocol as stored: a protocol edited by hand (a seed,
    max_steps) no longer matches it. MalformedRunError naming the field (from results.json's copy, when present)."""
    stored = manifest.get("protocol_hash")
    if not isinstance(stored, str):
        raise _fail(path, f"protocol_hash must be the protocol's sha256, got {_short(stored)} (every run records it)")
    if stored != protocol_hash(manifest["protocol"]):
        edited = _edited_fields(manifest["protocol"], path)
        named = (f"protocol.{', protocol.'.join(edited[:5])} differ(s) from results.json's copy" if edited
                 else "a field of protocol was changed")
        raise _fail(path, f"protocol does not match its protocol_hash ({named}): the manifest was edited by hand after "
                          "the run started")


def check_files_field(files, where: str) -> None:
    """The row's `files` value: {plain file name: {"size": int >= 0, "sha256": 64 hex digits}} (MalformedRunError)."""
    if not isinstance(files, dict):
        raise MalformedRunError(f"{where}: files must be an object of file digests, got {type(files).__name__}; {FIX}")
    for name, entry in files.items():
        if not (isinstance(name, str) and FILE_NAME.match(name) and name not in (".", "..")):
            raise MalformedRunError(f"{where}: files names {name!r}, not a file name inside the episode folder; {FIX}")
        if not (isinstance(entry, dict) and isinstance(entry.get("size"), int) and not isinstance(entry["size"], bool)
                and entry["size"] >= 0 and isinstance(entry.get("sha256"), str) and SHA256.match(entry["sha256"])):
            raise MalformedRunError(f"{where}: files[{name!r}] must be {{\"size\": bytes, \"sha256\": 64 hex digits}}; "
                                    f"{FIX}")


def parse_row(line: str, path: Path | str, number: int) -> Any:
    """One results.jsonl line (1-based `number`) -> its JSON value, or a MalformedRunError naming the line."""
    try:
        return loads_json(line, f"{path} line {number}")
    except BoundsError:
        raise
    except ValueError as exc:
        raise _fail(f"{path} line {number}", f"not JSON ({exc})") from None


def check_row(row: Any, path: Path | str, line: int,
              jobs: set[tuple[str, int]] | Mapping[tuple[str, int], int | None] | None = None) -> dict:
    """One results.jsonl row (1-based `line`): returns it unchanged or raises MalformedRunError. Its `directory`
    must be the folder the run writes for its job, `<task>/episode_<k>` (relative, so it cannot name a folder
    outside the run); its `files` digests are checked for form here and against the files by
    harness.runfolder.integrity."""
    where = f"{path} line {line}"
    _expect(where, "the row", row, (dict,), "a JSON object")
    _expect(where, "task", row.get("task"), (str,), "a task name")
    if not TASK_NAME.match(row["task"]):
        raise _fail(where, f"task {_short(row['task'])} is not a task name (its folder must lie inside the run)")
    _expect(where, "episode", row.get("episode"), (int,), "an integer")
    _expect(where, "seed", row.get("seed"), (int,), "an integer or null", optional=True)
    _expect(where, "steps", row.get("steps"), (int,), "an integer", optional=True)
    _expect(where, "success", row.get("success"), (bool,), "true or false", optional=True)
    status = row.get("status", "ok")
    if status not in ROW_STATUSES:
        raise _fail(where, f"status must be one of {ROW_STATUSES}, got {_short(status)}")
    if row.get("steps") is not None and row["steps"] < 0:
        raise _fail(where, f"steps must be >= 0, got {row['steps']}")
    if jobs is not None and (row["task"], row["episode"]) not in jobs:
        raise _fail(where, f"({row['task']!r}, episode {row['episode']}) is not one of the manifest's jobs")
    if isinstance(jobs, Mapping) and row.get("seed") is not None and jobs[(row["task"], row["episode"])] is not None \
            and row["seed"] != jobs[(row["task"], row["episode"])]:
        raise _fail(where, f"seed {row['seed']} is not its job's seed {jobs[(row['task'], row['episode'])]} "
                           "(manifest.json jobs): the row or the manifest was edited by hand")
    directory = row.get("directory")
    if directory is not None and directory != f"{row['task']}/episode_{row['episode']}":
        raise _fail(where, f"directory must be the job's folder {row['task']}/episode_{row['episode']!s} inside the run "
                           f"folder, got {_short(directory)}")
    if row.get("files") is not None:
        check_files_field(row["files"], where)
    if row.get("failure") is not None and row["failure"] not in FAILURE_KINDS:
        raise _fail(where, f"failure must be one of {FAILURE_KINDS}, got {_short(row['failure'])}")
    _expect(where, "lost", row.get("lost"), (str,), "a string", optional=True)
    retries = row.get("retries")
    if retries is not None and not (isinstance(retries, list) and all(
            isinstance(a, dict) and isinstance(a.get("lost"), str) and isinstance(a.get("cause"), str)
            and _is_int(a.get("step")) for a in retries)):
        raise _fail(where, f"retries must be a list of {{lost, cause, step}}, got {_short(retries)}")
    return row

"""Confinement and integrity of a run folder's files: a run folder is untrusted input (it may be copied, edited,
half-deleted or made by someone else), so every reader goes through these checks before using what it names.

Confinement: every path a run's files name (the run's own files, each row's episode folder, the files in it)
resolves, symlinks followed, inside the run folder. A path that leaves it or a symlink loop is a
`MalformedRunError` naming the file (one line, exit 2). The harness itself never writes a symlink.

Integrity: each finished episode's row in results.jsonl records `files`: {name: {"size": bytes, "sha256": hex}}
of its data files (`DATA_SUFFIXES`: the .npz arrays and the .jsonl tables), computed by the process that wrote
them. `episode_problem` says what is wrong with a finished episode (a file missing, a size or digest that differs
from the row's, a folder that is a symlink); readers raise it as a MalformedRunError naming the file, and
`run --resume` runs that episode again instead. Rows written before digests were recorded ("legacy rows") are
read unverified (confinement only; resume requires their episode.json, as it always did) and counted by readers.
"""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path

import zipfile

from harness.bounded import BoundsError, check_npz, file_kind
from harness.runfolder.schema import FIX, MalformedRunError

DATA_SUFFIXES = (".npz", ".jsonl", ".rrd")  # .rrd: a --rerun save recording, shown by `view` as the episode's own
VIEW_ONLY = (".rrd",)  # digested, but no command reads numbers from it: `view` checks it and rebuilds it when it differs
RECORDED = ("attention.npz", "actions.npz")  # written by every finished episode: a row with digests names them
LEGACY_RESUME = ("episode.json",)  # what resume requires of a finished episode whose row records no digests
RERUN = ("re-run that episode: octo-harness run --resume RUN_DIR (it runs damaged episodes again), or re-create the run "
         "with --overwrite")


def file_digest(path: str | os.PathLike, chunk: int = 1 << 20) -> dict:
    """{"size": bytes, "sha256": hex digest} of one file."""
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
            size += len(block)
    return {"size": size, "sha256": h.hexdigest()}


def data_digests(directory: str | os.PathLike, names) -> dict[str, dict]:
    """{name: file_digest} of the data files (`DATA_SUFFIXES`) among `names` in `directory`, sorted by name."""
    return {name: file_digest(Path(directory) / name) for name in sorted(set(names)) if name.endswith(DATA_SUFFIXES)}


def record_digests(run_dir: Path) -> None:
    """Rewrites the rows of a run folder cut down by a script (a committed baseline, a kept grid run: fewer or
    smaller files than the run wrote) so they record the digests of the files each episode folder now holds, in
    results.jsonl and results.json's copy. Rows of unfinished episodes, and rows whose folder is absent, stay as
    they are."""
    import json

    def digests(row: dict) -> dict:
        folder = run_dir / str(row.get("task")) / f"episode_{row.get('episode')}"
        if (row.get("status") or "ok") != "ok" or not folder.is_dir():
            return row
        return {**row, "files": data_digests(folder, os.listdir(folder))}

    lines = [json.loads(line) for line in (run_dir / "results.jsonl").read_text().splitlines() if line.strip()]
    (run_dir / "results.jsonl").write_text("".join(json.dumps(digests(r), sort_keys=True) + "\n" for r in lines))
    if (run_dir / "results.json").is_file():
        data = json.loads((run_dir / "results.json").read_text())
        data["episodes"] = [digests(r) for r in data.get("episodes", [])]
        (run_dir / "results.json").write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")


def _resolve(path: Path) -> tuple[Path | None, str | None]:
    """(the path with every symlink followed, None) or (None, why it cannot be: a loop)."""
    try:
        return Path(os.path.realpath(path, strict=True)), None
    except FileNotFoundError:  # absent, or a symlink to nothing: where it points is still checked
        try:
            return path.resolve(strict=False), None
        except (RuntimeError, OSError):
            return None, "is a symlink loop"
    except (RuntimeError, OSError) as exc:
        return None, "is a symlink loop" if getattr(exc, "errno", None) in (None, 40) else f"cannot be read ({exc})"


def inside(run_dir: Path, path: Path, named_by: str | None = None) -> Path:
    """`path` resolved (symlinks followed), or a MalformedRunError naming it when it loops or leaves `run_dir`
    (itself resolved). `named_by`: the file that names `path` (a row), said in the message."""
    root = Path(os.path.realpath(run_dir))
    resolved, why = _resolve(path)
    by = f" (named by {named_by})" if named_by else ""
    if resolved is None:
        raise MalformedRunError(f"{path}{by} {why}; {FIX}")
    if resolved != root and root not in resolved.parents:
        raise MalformedRunError(f"{path}{by} leads outside the run folder {root} (to {resolved}); {FIX}")
    return resolved


def check_run_files(run_dir: Path, names) -> None:
    """The run's own files (manifest.json, results.jsonl, ...): each that exists, even as a broken link, resolves
    inside the run folder and is a regular file (a FIFO, a device, a socket or a folder in its place is named here,
    from its `stat`, never opened: it is neither read as "no file" nor left to block a reader)."""
    for name in names:
        path = Path(run_dir) / name
        if os.path.lexists(path):
            inside(run_dir, path)
            try:
                mode = os.stat(path).st_mode
            except FileNotFoundError:  # a broken link: the file is absent
                continue
            kind = "a folder" if stat.S_ISDIR(mode) else file_kind(mode)
            if kind is not None:
                raise MalformedRunError(f"{path} is not a regular file (it is {kind}); {FIX}")


def array_axes(manifest: dict | None) -> dict[str, dict[int, int]]:
    """What the manifest implies about an episode's arrays: {member: {axis: size}} (layers, action horizon)."""
    model = (manifest or {}).get("model") or {}
    axes: dict[str, dict[int, int]] = {}
    if isinstance(model.get("layers"), int) and not isinstance(model["layers"], bool):
        axes["readout_attention"] = {1: model["layers"]}
    if isinstance(model.get("action_horizon"), int) and not isinstance(model["action_horizon"], bool):
        axes["predicted"] = {1: model["action_horizon"]}
    return axes


def arrays_problem(folder: Path, row: dict, manifest: dict | None) -> str | None:
    """The headers of every .npz in a finished episode's folder against its row (steps) and the manifest (layers,
    action horizon), before any array is loaded (harness.bounded.check_npz); a problem phrase or None."""
    steps = row.get("steps") if isinstance(row.get("steps"), int) else None
    axes = array_axes(manifest)
    for path in sorted(folder.glob("*.npz")):
        try:
            check_npz(path, steps, axes)
        except BoundsError as exc:
            return str(exc).split("; ")[0].rstrip(".")
        except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
            if path.name not in RECORDED:  # an optional file (controls, attribution): its section's reader leaves it out
                continue
            return f"{path} is damaged or incomplete ({type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else 'unreadable'})"
    return None


def episode_problem(run_dir: Path, directory: str, row: dict, where: str | None = None,
                    legacy: tuple[str, ...] = (), manifest: dict | None = None) -> str | None:
    """What is wrong with a finished episode's folder `run_dir/directory` as its `row` describes it, or None.

    A problem is a phrase starting with the path (e.g. ".../attention.npz is missing"). Confinement (a folder or a
    file that leads outside the run folder or loops) is raised as a MalformedRunError instead, except for the
    episode folder itself being a symlink, which is a problem (resume replaces it by a real folder). `where`: the row's
    place (e.g. "results.jsonl line 3"), named in a confinement error. `legacy`: the files required of a row that
    records no digests (readers: none, such a row is unverified; resume: episode.json, its completion mark); such a row
    still needs its arrays (`RECORDED`) when its folder exists or the manifest is one `run` wrote (it records the
    platform): only hand-made outcome-only run folders hold rows without episode files. `manifest`: the run's, whose
    model implies the arrays' layers and action horizon (`arrays_problem`)."""
    folder = Path(run_dir) / directory
    for link in (folder.parent, folder):
        if link.is_symlink():
            return f"{link} is a symlink, not a folder the run wrote"
    folder = inside(run_dir, folder, named_by=where)
    files = row.get("files")
    if files is None:
        made_by_run = isinstance(manifest, dict) and "platform_fingerprint" in manifest
        legacy = tuple(dict.fromkeys((*legacy, *(RECORDED if made_by_run or os.path.lexists(folder) else ()))))
        if not legacy:
            return None  # unverified: nothing recorded to check against, and no episode files to check
    if not folder.is_dir():
        return f"{folder} is {'not a folder' if os.path.lexists(folder) else 'missing'}"
    for root, dirs, names in os.walk(folder, followlinks=False):
        for name in dirs + names:
            entry = Path(root) / name
            if entry.is_symlink():
                inside(run_dir, entry)
    if files is not None:  # a row with digests records those of the arrays every finished episode writes
        for name in RECORDED:
            if name not in files:
                return f"{folder}: its row records no digest of {name} (every finished episode has one)"
    for name in legacy if files is None else ("episode.json", *files):
        path = folder / name
        if not path.is_file():
            return f"{path} is missing"
        if files is None or name not in files or name.endswith(VIEW_ONLY):
            continue  # a recording is checked by `view`, which rebuilds it from the arrays when it differs
        expected, found = files[name], file_digest(path)
        if found["size"] != expected["size"]:
            return f"{path} is damaged ({found['size']} bytes, its row records {expected['size']})"
        if found["sha256"] != expected["sha256"]:
            return f"{path} is damaged (its sha256 differs from the one its row records)"
    return arrays_problem(folder, row, manifest)


def verify_episode(run_dir: Path, directory: str, row: dict, where: str | None = None,
                   manifest: dict | None = None) -> None:
    """A reader's check of a finished episode: a MalformedRunError (one line, naming the file and the fix) when
    `episode_problem` finds one."""
    problem = episode_problem(run_dir, directory, row, where, manifest=manifest)
    if problem is not None:
        raise MalformedRunError(f"{problem}; {RERUN}")

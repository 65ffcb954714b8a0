"""Run folders -> typed records: the one reader of what `octo-harness run` leaves on disk.

`load_run(path)` reads a run folder's metadata (no arrays) into a `RunRecord`; `load_episode_arrays(ep)`
reads one episode's attention.npz into an `EpisodeArrays`. Two layouts are read:

- "octo-harness-run/1" (the run store): manifest.json + results.jsonl (source of truth, one line per
  finished episode, the last line of a job wins) + results.json (only for its "status").
- "legacy": results.json holding {"manifest": ..., "episodes": [...]} (runs made before the run store).

Readers must tolerate a run in progress or interrupted (fewer episodes than jobs: `RunRecord.missing`),
failed episodes (status "failed", no arrays), runs without masks (no mask arrays) and runs of a policy without
attention (`RunRecord.attention` False: attention.npz holds step and phase only, `no_attention_line` says so). A folder that is
not a run raises `NotARunError` with one line naming the fix.

A run folder is untrusted input: `load_run` checks (harness/runfolder/) that the run's files and every finished
episode's folder and files lie inside the run folder, and that each finished episode's data files match the size
and sha256 its row records (rows written before digests were recorded are read unverified and counted in
`RunRecord.unverified`). What fails is a MalformedRunError naming the file (one line, exit 2).
"""

from __future__ import annotations

import logging
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from harness.bounded import BoundsError, loads_json, read_json, read_jsonl_text
from harness.bounded import read_npz as bounded_npz
from harness.runfolder.integrity import check_run_files, inside, verify_episode
from harness.runfolder.schema import MalformedRunError, check_manifest, check_row, parse_row

RUN_FORMAT = "octo-harness-run/1"
RUN_FILES = ("manifest.json", "results.jsonl", "results.json")

log = logging.getLogger(__name__)


class NotARunError(ValueError):
    """The folder is not an octo-harness run (one-line message naming the fix)."""


@dataclass(frozen=True)
class ModelInfo:
    source: str  # e.g. "hf://rail-berkeley/octo-small-1.5", "random:octo-small-1.5", a checkpoint folder
    is_random: bool  # random weights: actions and attention are not a trained policy's
    note: str
    text_tokenizer: str | None
    dataset_key: str | None


@dataclass(frozen=True)
class EpisodeRecord:
    """One finished job (a row of results.jsonl / results.json)."""

    task: str
    episode: int
    seed: int | None
    status: str  # "ok" | "failed" (the episode raised; no arrays)
    success: bool
    steps: int
    directory: Path  # absolute episode folder
    error: str | None = None
    row: dict = field(default_factory=dict, compare=False, repr=False)  # the raw result row

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def attention_path(self) -> Path:
        return self.directory / "attention.npz"

    @property
    def video_path(self) -> Path | None:
        path = self.directory / "rollout.mp4"
        return path if path.is_file() else None

    def read_json(self) -> dict:
        """episode.json ({} when absent or unreadable)."""
        try:
            return read_json(self.directory / "episode.json")
        except BoundsError:
            raise
        except (OSError, ValueError):
            return {}


@dataclass(frozen=True)
class RunRecord:
    path: Path  # absolute run folder
    name: str
    format: str  # RUN_FORMAT or "legacy"
    status: str  # "complete" | "running" | "interrupted" | "incomplete" (legacy runs cannot tell the last two apart)
    model: ModelInfo
    tasks: tuple[str, ...]  # in protocol order
    jobs: tuple[tuple[str, int, int | None], ...]  # (task, episode, seed) the run was asked to do
    episodes: tuple[EpisodeRecord, ...]  # finished jobs, in job order
    manifest: dict = field(compare=False, repr=False)
    versions: dict = field(default_factory=dict, compare=False)
    git_commit: str | None = None
    created: str | None = None
    unverified: int = 0  # finished episodes whose rows record no file digests (made before digests were recorded)

    @property
    def attention(self) -> bool:
        """Whether the run's policy gave attention: False when the manifest records a model without attention layers
        (a policy without attention, e.g. a served one: its episodes' attention.npz hold step and phase only)."""
        model = self.manifest.get("model") if isinstance(self.manifest, dict) else None
        return not (isinstance(model, dict) and "layers" in model and model["layers"] is None)

    @property
    def missing(self) -> int:
        """Jobs without a result yet (run in progress or interrupted)."""
        done = {(e.task, e.episode) for e in self.episodes}
        return sum((task, k) not in done for task, k, _ in self.jobs)

    def missing_by_task(self) -> dict[str, int]:
        done = {(e.task, e.episode) for e in self.episodes}
        return {task: sum(t == task and (t, k) not in done for t, k, _ in self.jobs) for task in self.tasks}

    def task_episodes(self, task: str) -> tuple[EpisodeRecord, ...]:
        return tuple(e for e in self.episodes if e.task == task)


@dataclass(frozen=True, eq=False)
class EpisodeArrays:
    """What the report needs from one attention.npz (see harness/outputs/writers.py)."""

    readout_attention: np.ndarray  # (steps, layers, heads, readouts, keys) float16
    tokens: dict[str, np.ndarray]  # tokens/* arrays (TokenMap.from_arrays reads them)
    mask_fractions: dict[str, np.ndarray]  # "<obs>/<name>" -> (steps, rows, cols) patch coverage; {} for older runs
    mask_areas: dict[str, np.ndarray]  # "<obs>/<name>" -> (steps,) pixel fraction inside the mask
    mask_mass: dict[str, np.ndarray]  # "<obs>/<name>" -> (steps, layers) stored head-mean mask mass (metrics/mask_mass)
    step: np.ndarray  # (steps,) int


def _read_json(path: Path) -> dict:
    try:
        return read_json(path)
    except BoundsError:
        raise
    except ValueError as exc:
        raise NotARunError(f"{path} is not valid JSON ({exc}); the run folder is damaged") from None


def _not_a_run(path: Path) -> NotARunError:
    if not path.exists():
        return NotARunError(f"{path} does not exist; pass a run folder made by `octo-harness run` (e.g. results/runs/<run>)")
    if not path.is_dir():
        return NotARunError(f"{path} is not a folder; pass a run folder made by `octo-harness run` (e.g. results/runs/<run>)")
    inside = sorted(p.name for p in path.iterdir() if p.is_dir() and ((p / "manifest.json").is_file() or (p / "results.json").is_file()))
    if inside:
        shown = ", ".join(inside[:5]) + (", ..." if len(inside) > 5 else "")
        return NotARunError(f"{path} holds runs ({shown}), it is not one itself; pass one of them, e.g. {path / inside[0]}")
    return NotARunError(f"{path} is not an octo-harness run folder (no manifest.json or results.json); "
                        "pass a folder made by `octo-harness run` (e.g. results/runs/<run>)")


def is_run_dir(path: str | Path) -> bool:
    path = Path(path)
    return (path / "manifest.json").is_file() or (path / "results.json").is_file()


def load_run(path: str | Path, legacy: bool = True) -> RunRecord:
    """Read a run folder's manifest and results (not the arrays). Raises NotARunError for anything else.
    legacy=False (compare, regress): a folder without manifest.json is not a run, whatever its results.json says."""
    path = Path(path).resolve()
    check_run_files(path, RUN_FILES)  # a symlink loop or a link out of the folder is named, not read as "no file"
    if (path / "manifest.json").is_file():
        return _load_store_run(path)
    if (path / "results.json").is_file():
        data = _read_json(path / "results.json")
        store_made = isinstance(data, dict) and isinstance(data.get("manifest"), dict) \
            and data["manifest"].get("format") == RUN_FORMAT
        if store_made or not legacy:  # the run store's derived copy: its record (manifest.json) is gone
            raise NotARunError(f"{path / 'manifest.json'} is missing; results.json is derived from it and cannot stand "
                               "in for the run's record: restore manifest.json or re-create the run "
                               "(octo-harness run ... --overwrite)")
        return _load_legacy_run(path, data)
    raise _not_a_run(path)


def _episode(row: dict, run_dir: Path) -> EpisodeRecord:
    """The row as a record; its folder is `<run>/<task>/episode_<k>` (the schema holds a row's directory to it)."""
    task, k = str(row["task"]), int(row["episode"])
    directory = run_dir / task / f"episode_{k}"
    seed = row.get("seed")
    return EpisodeRecord(
        task=task,
        episode=k,
        seed=None if seed is None else int(seed),
        status=str(row.get("status") or "ok"),
        success=bool(row.get("success")),
        steps=int(row.get("steps") or 0),
        directory=directory,
        error=row.get("error"),
        row=row,
    )


def _model_info(model: dict | None, legacy: dict) -> ModelInfo:
    model = model or {}
    source = model.get("source") or legacy.get("model") or "unknown"
    is_random = model.get("is_random", legacy.get("model_is_random"))
    if is_random is None:
        is_random = str(source).startswith("random:")
    return ModelInfo(
        source=str(source),
        is_random=bool(is_random),
        note=str(model.get("note") or legacy.get("model_note") or ""),
        text_tokenizer=model.get("text_tokenizer", legacy.get("text_tokenizer")),
        dataset_key=model.get("dataset_key", legacy.get("dataset_key")),
    )


def _ordered(episodes: list[EpisodeRecord], jobs: list[tuple[str, int, int | None]]) -> tuple[EpisodeRecord, ...]:
    order = {(t, k): i for i, (t, k, _) in enumerate(jobs)}
    return tuple(sorted(episodes, key=lambda e: (order.get((e.task, e.episode), len(order)), e.task, e.episode)))


def _load_store_run(path: Path) -> RunRecord:
    manifest = _read_json(path / "manifest.json")
    if not isinstance(manifest, dict) or "jobs" not in manifest:
        raise NotARunError(f"{path / 'manifest.json'} has no 'jobs'; it is not an octo-harness run manifest")
    check_manifest(manifest, path / "manifest.json")
    protocol = manifest.get("protocol") or {}
    jobs = [(t, k, s) for t, k, s in manifest["jobs"]]
    keys = {(t, k): s for t, k, s in jobs}
    rows: dict[tuple[str, int], dict] = {}
    results = path / "results.jsonl"
    if results.is_file():
        text = read_jsonl_text(results)
        lines = text.splitlines()
        for number, line in enumerate(lines, 1):
            if not line.strip():
                continue
            if number == len(lines) and not text.endswith("\n"):
                try:  # the last line may be being appended right now
                    loads_json(line, f"{results} line {number}")
                except BoundsError:
                    raise
                except ValueError:
                    continue
            row = check_row(parse_row(line, results, number), results, number, keys)
            rows[(row["task"], row["episode"])] = (row, number)  # the last line of a job wins
    unverified = 0
    for row, number in rows.values():
        if (row.get("status") or "ok") == "ok":
            verify_episode(path, f"{row['task']}/episode_{row['episode']}", row, f"{results} line {number}", manifest)
            unverified += row.get("files") is None
    if unverified:
        log.info("%s: %d finished episodes record no file digests (rows made before digests were recorded); their "
                 "files are read unverified", path, unverified)
    episodes = [_episode(row, path) for row, _ in rows.values()]
    status = None
    if (path / "results.json").is_file():
        try:
            status = read_json(path / "results.json").get("status")
        except BoundsError:
            raise
        except (OSError, ValueError, AttributeError):
            status = None
    done = {(e.task, e.episode) for e in episodes}
    if all((t, k) in done for t, k, _ in jobs):
        status = "complete"
    elif status not in ("running", "interrupted"):
        status = "incomplete"
    tasks = tuple(protocol.get("tasks") or dict.fromkeys(t for t, _, _ in jobs))
    return RunRecord(
        path=path,
        name=str(manifest.get("run") or path.name),
        format=str(manifest.get("format") or RUN_FORMAT),
        status=status,
        model=_model_info(manifest.get("model"), {**protocol, **manifest}),
        tasks=tasks,
        jobs=tuple(jobs),
        episodes=_ordered(episodes, jobs),
        manifest=manifest,
        versions=dict(manifest.get("versions") or {}),
        git_commit=manifest.get("git_commit"),
        created=manifest.get("created"),
        unverified=unverified,
    )


def _load_legacy_run(path: Path, data) -> RunRecord:
    if not isinstance(data, dict) or "manifest" not in data or "episodes" not in data:
        raise NotARunError(f"{path / 'results.json'} has no manifest and episodes; it is not an octo-harness run")
    manifest = data["manifest"]
    tasks = tuple(str(t) for t in manifest.get("tasks") or dict.fromkeys(r["task"] for r in data["episodes"]))
    seed0 = int(manifest.get("seed") or 0)
    jobs = [(t, k, seed0 + k) for t in tasks for k in range(int(manifest.get("episodes") or 0))]
    episodes = {(str(r["task"]), int(r["episode"])): _episode(r, path) for r in data["episodes"]}
    for ep in episodes.values():  # recorded paths (absolute, of a moved folder) are not followed: <run>/<task>/episode_<k>
        inside(path, ep.directory, named_by=str(path / "results.json"))
    done = set(episodes)
    status = "complete" if all((t, k) in done for t, k, _ in jobs) else "incomplete"
    return RunRecord(
        path=path,
        name=path.name,
        format="legacy",
        status=status,
        model=_model_info(None, manifest),
        tasks=tasks,
        jobs=tuple(jobs),
        episodes=_ordered(list(episodes.values()), jobs),
        manifest=manifest,
        versions=dict(manifest.get("versions") or {}),
        git_commit=manifest.get("git_commit"),
        created=data.get("created"),
    )


def no_attention_line(runs, where: str = "") -> str | None:
    """One line naming the runs (RunRecord, or anything with `.record`) whose policy gave no attention, or None."""
    records = [getattr(r, "record", r) for r in runs]
    without = [r for r in records if not r.attention]
    if not without:
        return None
    names = ", ".join(f"{r.name} ({r.model.source})" for r in without)
    return (f"no attention{' ' + where if where else ''}: {names} "
            f"{'gives' if len(without) == 1 else 'give'} actions only (a policy without attention, e.g. a served one)")


def load_episode_arrays(episode: EpisodeRecord) -> EpisodeArrays:
    """Read attention.npz of a finished episode. Raises FileNotFoundError when it is absent, MalformedRunError (a
    ValueError, one line) when it is damaged."""
    z = read_npz(episode.attention_path, steps=episode.steps or None)
    if "readout_attention" not in z:
        raise _damaged(episode.attention_path, ValueError("it has no readout_attention"))

    def group(prefix: str) -> dict[str, np.ndarray]:
        return {name[len(prefix):]: value for name, value in z.items() if name.startswith(prefix)}

    return EpisodeArrays(
        readout_attention=z["readout_attention"],
        tokens={name: value for name, value in z.items() if name.startswith("tokens/")},
        mask_fractions=group("mask_fraction/"),
        mask_areas=group("metrics/mask_area/"),
        mask_mass=group("metrics/mask_mass/"),
        step=z["step"] if "step" in z else np.arange(z["readout_attention"].shape[0]),
    )


def read_npz(path: Path, *names: str, steps: int | None = None) -> dict[str, np.ndarray]:
    """An episode's .npz as {name: array} (only `names` when given), its headers checked before any data is loaded
    (harness.bounded: no array longer than `steps`, none over the stated byte limits). A damaged or cut-short file
    (a full disk, a killed copy) is a MalformedRunError naming it and the fix (one line, exit 2), not a traceback;
    a missing one is FileNotFoundError."""
    try:
        return bounded_npz(path, names, steps=steps)
    except FileNotFoundError:
        raise
    except BoundsError:
        raise
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise _damaged(path, exc) from None


def _damaged(path: Path, exc: BaseException) -> MalformedRunError:
    detail = str(exc).splitlines()[0] if str(exc) else "unreadable"
    return MalformedRunError(f"{path} is damaged or incomplete ({type(exc).__name__}: {detail}); re-run that "
                             "episode (octo-harness run --resume ... --retry-failed, or --overwrite)")

"""Keep a robustness grid's finished episodes small enough to commit, so a grid longer than one machine's life goes on
where the last machine stopped (issue 74: the reference grids take about 8 hours on 2 cores; a session's machine lasts
3).

    .venv/bin/python scripts/keep_grid_runs.py keep results/robustness-reference results/grids/robustness-reference
    .venv/bin/python scripts/keep_grid_runs.py restore results/grids/robustness-reference results/robustness-reference

`keep GRID DEST` writes DEST/<run>.tar.xz, the kept copy of each run of the grid folder GRID, and DEST/index.json (the
finished episodes each archive holds); a run whose count has not changed keeps its archive byte for byte. A kept run
holds the run's own files (manifest, results, summaries, the grid's robustness.json, KEPT.json) and, per finished
episode, episode.json and what the EVAL.md sections and `octo-harness diagnose` read:
  attention.npz          step, phase, tokens/* and, at the model's last layer only, the per-step measures (entropy; the
                         primary camera's target lift and mass on the target, gripper, background and distractors;
                         every camera's mass on every mask where the episode has reliance, for the Reliance section's
                         attention shares), as recorded, so the sections come out the same as from the full run;
  actions.npz            step, reward, success;
  action_consistency.npz step and disagreement;
  readout_features.npz, reliance.jsonl  whole.
PNG, MP4, metrics.jsonl and the attention maps are dropped: 7-16 KB an episode in the archive instead of 0.3-3 MB.
Each row's file digests are those of the kept files, so the run store reads a kept run as any run, and `robustness`
on the grid folder skips its finished episodes (resume). Paths stay as recorded: the protocol names the model by its
absolute path, and a run resumes only under the protocol it was made with (run the grid from the same checkout path).

`restore KEPT GRID` extracts every archive whose run GRID does not hold yet (a run GRID holds is the fuller copy).
A kept run is enough for the Robustness, Reliance and Failure early warning sections; the HTML report of it has no
attention maps.
"""
from __future__ import annotations

import argparse
import json
import os
import lzma
import shutil
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from harness.analysis.compare import GRID_FILE  # noqa: E402
from harness.files import atomic_write_json, write_atomic  # noqa: E402
from harness.runfolder.integrity import record_digests  # noqa: E402

RUN_FILES = ("manifest.json", "results.jsonl", "results.json", "summary.csv", "statistics.csv")
MARKER = "KEPT.json"
INDEX = "index.json"
CAMERA = "image_primary"
WHOLE = ("readout_features.npz", "reliance.jsonl")
# what diagnose and the sections read, at the last layer: the entropy, the target's lift and the primary camera's mass
# on the target, gripper, background and distractors (every mask of every camera where the episode has reliance)
MEASURES = ("measures/layer/entropy", f"measures/layer/mask_lift/{CAMERA}/target")
MASS = "measures/layer/mask_mass/"
PRIMARY_MASKS = ("target", "gripper", "background", "distractor_")


def _kept_attention(z, reliance: bool) -> dict[str, np.ndarray]:
    """The arrays of attention.npz the sections and diagnose read; with `reliance` (the episode has reliance.jsonl)
    every camera's mass on every mask, which the Reliance section's attention shares use."""
    wanted = (MASS,) if reliance else tuple(f"{MASS}{CAMERA}/{m}" for m in PRIMARY_MASKS)
    out = {}
    for key in z.files:
        if key in ("step", "phase", "phase_names") or key.startswith("tokens/"):
            out[key] = z[key]
        elif key in MEASURES or key.startswith(wanted):
            out[key] = z[key][:, -1:]
    return out


def _kept_arrays(name: str, z, reliance: bool) -> dict[str, np.ndarray]:
    if name == "attention.npz":
        return _kept_attention(z, reliance)
    if name == "actions.npz":
        return {k: z[k] for k in ("step", "reward", "success") if k in z.files}
    if name == "action_consistency.npz":
        return {k: z[k] for k in ("step", "disagreement") if k in z.files}
    raise ValueError(name)


def keep_episode(src: Path, dst: Path) -> None:
    dst.mkdir(parents=True)
    shutil.copy2(src / "episode.json", dst / "episode.json")
    for name in ("attention.npz", "actions.npz", "action_consistency.npz"):
        if (src / name).is_file():
            with np.load(src / name) as z:
                arrays = _kept_arrays(name, z, (src / "reliance.jsonl").is_file())
            write_atomic(dst / name, lambda f: np.savez(f, **arrays))
    for name in WHOLE:
        if (src / name).is_file():
            shutil.copy2(src / name, dst / name)


def _rows(path: Path) -> list[dict]:
    """results.jsonl's rows; a last line still being written by a running grid is left for the next keep."""
    rows = []
    for line in path.read_text().splitlines() if path.is_file() else ():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return rows


def keep_run(src: Path, dst: Path) -> int:
    """Kept copy of one run folder; the number of finished episodes kept. Rows of episodes not finished (no folder
    with episode.json, or a failed status) are kept as they are, so a resume runs what the run had left."""
    dst.mkdir(parents=True)
    for name in RUN_FILES:
        if (src / name).is_file():
            shutil.copy2(src / name, dst / name)
    kept = 0
    out = []
    for row in _rows(src / "results.jsonl"):
        if (row.get("status") or "ok") == "ok" and row.get("files") is not None:
            folder = f"{row['task']}/episode_{row['episode']}"
            if not (src / folder / "episode.json").is_file():
                continue
            if not (dst / folder).exists():
                keep_episode(src / folder, dst / folder)
                kept += 1
        out.append(row)
    (dst / "results.jsonl").write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in out))
    record_digests(dst)  # the rows name the kept files, so a resume and every reader verify them as any run's
    return kept


def _finished(run: Path) -> int:
    return sum(1 for r in _rows(run / "results.jsonl") if (r.get("status") or "ok") == "ok" and r.get("files") is not None)


def _reset(info: tarfile.TarInfo) -> tarfile.TarInfo:
    info.mtime, info.uid, info.gid, info.uname, info.gname = 0, 0, 0, "", ""
    return info


def _tar_xz(folder: Path, archive: Path) -> None:
    """folder -> archive (.tar.xz), entries sorted and owner and times cleared; written beside it and renamed."""
    tmp = archive.with_name(archive.name + f".tmp.{os.getpid()}")
    with lzma.open(tmp, "wb", preset=9) as raw, tarfile.open(fileobj=raw, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for path in [folder, *sorted(folder.rglob("*"))]:
            tar.add(path, arcname=path.relative_to(folder.parent).as_posix(), recursive=False, filter=_reset)
    tmp.rename(archive)


def keep(grid: Path, dest: Path) -> list[str]:
    """DEST/<run>.tar.xz for every run of GRID whose finished episodes differ in number from its archive's (an
    unchanged run keeps its archive byte for byte); DEST/index.json {run: finished episodes}. The runs written."""
    dest.mkdir(parents=True, exist_ok=True)
    index_path = dest / INDEX
    index = json.loads(index_path.read_text()) if index_path.is_file() else {}
    written = []
    for run in sorted(p for p in grid.iterdir() if (p / "manifest.json").is_file()):
        finished = _finished(run)
        if index.get(run.name) == finished and (dest / f"{run.name}.tar.xz").is_file():
            continue
        with tempfile.TemporaryDirectory(dir=dest, prefix=".keep-") as tmp:
            folder = Path(tmp) / run.name
            keep_run(run, folder)
            if (grid / GRID_FILE).is_file():
                shutil.copy2(grid / GRID_FILE, folder / GRID_FILE)
            (folder / MARKER).write_text(json.dumps({
                "source_grid": grid.name, "finished_episodes": finished, "script": "scripts/keep_grid_runs.py",
                "note": "per finished episode: outcome, phases, the last layer's measures that diagnose and the "
                        "robustness sections read, action disagreement, readout features and reliance; "
                        "PNG, MP4, metrics.jsonl and the attention maps dropped"}, indent=2) + "\n")
            _tar_xz(folder, dest / f"{run.name}.tar.xz")
        index[run.name] = finished
        written.append(run.name)
    atomic_write_json(index_path, dict(sorted(index.items())))
    return written


def restore(kept: Path, grid: Path) -> list[str]:
    """Extract every DEST/<run>.tar.xz whose run GRID does not hold (a run GRID holds is the fuller copy)."""
    grid.mkdir(parents=True, exist_ok=True)
    restored = []
    for archive in sorted(kept.glob("*.tar.xz")):
        name = archive.name[: -len(".tar.xz")]
        if (grid / name).exists():
            continue
        with tempfile.TemporaryDirectory(dir=grid, prefix=".restore-") as tmp:
            try:
                with tarfile.open(archive, "r:xz") as tar:
                    tar.extractall(tmp, filter="data")
            except (tarfile.TarError, lzma.LZMAError, EOFError, OSError) as exc:
                raise SystemExit(f"keep_grid_runs.py: {archive} is damaged ({type(exc).__name__}: {exc}); check it out "
                                 "again (git checkout -- FILE), or delete it and run its grid cells again") from None
            if not (Path(tmp) / name / "manifest.json").is_file():
                raise SystemExit(f"keep_grid_runs.py: {archive} holds no run {name}/; delete it and keep the grid again")
            if (Path(tmp) / name / GRID_FILE).is_file():
                grid_file = Path(tmp) / name / GRID_FILE
                if not (grid / GRID_FILE).is_file():
                    shutil.copy2(grid_file, grid / GRID_FILE)
                grid_file.unlink()
            (Path(tmp) / name).rename(grid / name)
        restored.append(name)
    return restored


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    k = sub.add_parser("keep", help="GRID DEST: kept copy of every run of a grid folder")
    k.add_argument("grid", type=Path)
    k.add_argument("dest", type=Path)
    r = sub.add_parser("restore", help="KEPT GRID: copy kept runs the grid folder does not hold into it")
    r.add_argument("kept", type=Path)
    r.add_argument("grid", type=Path)
    args = parser.parse_args()
    if args.command == "keep":
        if not args.grid.is_dir():
            raise SystemExit(f"keep_grid_runs.py: {args.grid} is not a folder; give a robustness grid folder")
        names = keep(args.grid, args.dest)
        size = sum(p.stat().st_size for p in args.dest.glob("*.tar.xz"))
        print(f"kept {len(names)} runs anew in {args.dest} ({size / 1024:.0f} KiB in all): {', '.join(names) or 'none'}")
    else:
        if not args.kept.is_dir():
            print(f"keep_grid_runs.py: no kept runs at {args.kept}; nothing to restore")
            return 0
        names = restore(args.kept, args.grid)
        print(f"restored {len(names)} runs into {args.grid}: {', '.join(names) or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

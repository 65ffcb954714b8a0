"""Make a committed baseline from a finished run: results/baselines/<name>/ (small enough for git).

    .venv/bin/octo-harness run --task Lift --episodes 2 --model models/octo-reference-robosuite \
        --fast-render --png-every 0 --no-video --out /tmp/runs --run-name baseline
    .venv/bin/python scripts/make_baseline.py /tmp/runs/baseline results/baselines/reference-lift

Keeps manifest.json, results.jsonl, results.json, summary.csv and per episode episode.json plus actions.npz,
attention.npz and (for runs made with --record-inputs) inputs.npz cut to the first --steps steps (default 20:
what `octo-harness replay` compares the model on, on any machine); drops PNG, MP4, GIF and metrics.jsonl. BASELINE.json records where it came from and how to find the model again
("model_ref": "repo:<path inside the repository>" or "fixture:<name>"); harness.analysis.compare reads it to
compare arrays over the stored steps only. The rows record the size and sha256 of the cut files. Paths into the
repository are written relative to its root, and the source run by its folder name: a baseline names no machine's
folders. The destination is replaced atomically (built next to it, renamed).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from harness.analysis.compare import BASELINE_MARKER  # noqa: E402
from harness.analysis.runs import load_run  # noqa: E402
from harness.files import atomic_write_json, write_atomic  # noqa: E402
from harness.runfolder.integrity import record_digests  # noqa: E402
from harness.runfolder.schema import protocol_hash  # noqa: E402

KEEP_RUN_FILES = ("manifest.json", "results.jsonl", "results.json", "summary.csv", "statistics.csv")


def model_ref(source: str) -> str:
    """How the gate test finds the model again: inside the repository, or a reference fixture by name."""
    path = Path(source)
    if path.is_absolute():
        try:
            return "repo:" + path.resolve().relative_to(REPO).as_posix()
        except ValueError:
            if path.parent.name == "octo-reference":
                return "fixture:" + path.name
    return source  # hf://..., random:...


def repository_relative(folder: Path, repo: Path = REPO) -> None:
    """Rewrite every absolute path into this repository, in the kept JSON files of `folder`, as a path relative to the
    repository root: a committed baseline names no machine's folders (the gate and replay find the model through
    BASELINE.json's model_ref, never through these fields). The protocol names its model by path, so the manifest's
    protocol_hash (and results.json's copy of it) is recomputed for the protocol as rewritten."""
    prefix = repo.resolve().as_posix()
    for path in sorted(folder.rglob("*")):
        if path.is_file() and path.suffix in (".json", ".jsonl"):
            text = path.read_text()
            new = text.replace(f'"{prefix}"', '"."').replace(prefix + "/", "")
            if new != text:
                path.write_text(new)
    for name, key in (("manifest.json", None), ("results.json", "manifest")):
        if (folder / name).is_file():
            data = json.loads((folder / name).read_text())
            manifest = data[key] if key else data
            if isinstance(manifest, dict) and "protocol" in manifest:
                manifest["protocol_hash"] = protocol_hash(manifest["protocol"])
                atomic_write_json(folder / name, data)


def cut_npz(src: Path, dst: Path, steps: int) -> None:
    """Copy an episode array file keeping the first `steps` entries of every per-step array (tokens/* whole)."""
    with np.load(src) as z:
        arrays = {k: (z[k] if k.startswith("tokens/") or z[k].ndim == 0 else z[k][:steps]) for k in z.files}
    write_atomic(dst, lambda f: np.savez_compressed(f, **arrays))


def make_baseline(run_dir: Path, dest: Path, steps: int = 1) -> Path:
    run = load_run(run_dir)
    if run.format == "legacy":
        raise SystemExit(f"error: {run_dir} was made before the run store; re-run it with this octo-harness")
    if run.status != "complete" or any(not e.ok for e in run.episodes):
        raise SystemExit(f"error: {run_dir} is {run.status} or has failed episodes; a baseline needs a complete, clean run")
    tmp = dest.with_name(dest.name + f".tmp.{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name in KEEP_RUN_FILES:
        if (run.path / name).is_file():
            shutil.copy2(run.path / name, tmp / name)
    for episode in run.episodes:
        rel = episode.directory.relative_to(run.path)
        (tmp / rel).mkdir(parents=True)
        shutil.copy2(episode.directory / "episode.json", tmp / rel / "episode.json")
        for name in ("actions.npz", "attention.npz", "inputs.npz"):
            if (episode.directory / name).is_file():  # inputs.npz: runs made with --record-inputs (replay)
                cut_npz(episode.directory / name, tmp / rel / name, steps)
    repository_relative(tmp)
    record_digests(tmp)  # the rows name the cut arrays, so readers verify the baseline as any run
    (tmp / BASELINE_MARKER).write_text(json.dumps({
        "source_run": run.path.name, "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "arrays_steps": steps, "model_ref": model_ref(run.model.source),
        "model_fingerprint": (run.manifest.get("protocol") or {}).get("model_fingerprint"),
        "recorded_inputs": all((e.directory / "inputs.npz").is_file() for e in run.episodes),
        "note": "arrays (and recorded inputs) keep only the first steps; PNG, MP4 and metrics.jsonl are dropped",
    }, indent=2) + "\n")
    if dest.exists():
        old = dest.with_name(dest.name + f".old.{os.getpid()}")
        dest.rename(old)
        tmp.rename(dest)
        shutil.rmtree(old)
    else:
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp.rename(dest)
    return dest


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a complete run folder")
    parser.add_argument("dest", type=Path, help="baseline folder, e.g. results/baselines/reference-lift")
    parser.add_argument("--steps", type=int, default=20, help="steps of arrays and recorded inputs to keep per episode [20]")
    args = parser.parse_args()
    dest = make_baseline(args.run, args.dest, args.steps)
    size = sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())
    print(f"baseline: {dest} ({size / 1024:.0f} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

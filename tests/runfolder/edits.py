"""Test helper: edit a copied run folder's episode files as an older or foreign run would hold them, then record
their sizes and digests in results.jsonl as if the run had written them (the readers refuse files whose digests
differ from the row's; see harness/runfolder/integrity.py)."""

import json
from pathlib import Path

from harness.runfolder.integrity import data_digests


def redigest(run_dir: Path) -> None:
    """Re-record every finished row's `files` from the files now in its episode folder."""
    results = Path(run_dir) / "results.jsonl"
    rows = [json.loads(line) for line in results.read_text().splitlines() if line.strip()]
    for row in rows:
        if row.get("files"):
            row["files"] = data_digests(Path(run_dir) / row["directory"], list(row["files"]))
    results.write_text("".join(json.dumps(row) + "\n" for row in rows))


def rehash(run_dir: Path) -> None:
    """Re-record manifest.json's protocol_hash after a test edited its protocol on purpose (e.g. to name this
    checkout's copy of a model): readers refuse a protocol that no longer matches its recorded hash."""
    from harness.runfolder.schema import protocol_hash

    path = Path(run_dir) / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["protocol_hash"] = protocol_hash(manifest["protocol"])
    path.write_text(json.dumps(manifest))


def drop_output(run_dir: Path, name: str, rows: int | None = None) -> None:
    """Delete episode file `name` (e.g. "inputs.npz") and its record in the first `rows` finished rows (all by
    default), as a run made without that output holds them: the readers then see an output that was never written,
    not a written file that went missing."""
    results = Path(run_dir) / "results.jsonl"
    kept = [json.loads(line) for line in results.read_text().splitlines() if line.strip()]
    for row in kept[:rows]:
        (Path(run_dir) / row["directory"] / name).unlink(missing_ok=True)
        if row.get("files"):
            row["files"].pop(name, None)
    results.write_text("".join(json.dumps(row) + "\n" for row in kept))


def make_legacy(run_dir: Path) -> None:
    """Drop every row's recorded sizes and digests, as rows written before they were recorded hold them (the
    readers then read the files unverified, and a damaged one is found by its own reader)."""
    results = Path(run_dir) / "results.jsonl"
    rows = [json.loads(line) for line in results.read_text().splitlines() if line.strip()]
    for row in rows:
        row.pop("files", None)
    results.write_text("".join(json.dumps(row) + "\n" for row in rows))


MASK_PREFIXES = ("mask_fraction/", "metrics/mask_", "measures/layer/mask_", "measures/head/mask_")


def strip_masks(run_dir: Path) -> None:
    """Drop every mask measure from the episodes' attention.npz and re-record the digests, as a --no-masks run
    writes them (without paying for a second run)."""
    import numpy as np

    for npz in Path(run_dir).glob("*/episode_*/attention.npz"):
        with np.load(npz) as z:
            kept = {k: z[k] for k in z.files if not k.startswith(MASK_PREFIXES)}
        np.savez(npz, **kept)
    redigest(run_dir)

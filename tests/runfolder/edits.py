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

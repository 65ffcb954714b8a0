"""Digest every file under a golden-runs folder (scripts/golden_runs.sh): one line `sha256  path` per file, sorted.

Fields that differ between two runs of the same code on one machine are blanked before hashing: wall-clock times
(`timings`), durations, dates, commits, host paths and the run folder's own name (`run`). JSON and JSONL are parsed and re-serialised with those
keys removed, CSV without those columns; HTML and Markdown have the golden folder's path replaced; everything else (npz, PNG, MP4, CSV) is
hashed as written. An npz is hashed member by member (its zip headers hold file times).
"""

from __future__ import annotations

import csv
import hashlib
import json
import re
import sys
import zipfile
from pathlib import Path

VOLATILE = re.compile(r"(^run$|time|timing|seconds|per_step$|overhead|duration|started|finished|date|elapsed|host|pid|created|updated|wall|_at$|"
                      r"commit|python|platform_detail)", re.I)


TIMED_FILES = ("metrics.jsonl", "episode.json")  # their digests, recorded in results.json, cover their timings


def scrub(value):
    if isinstance(value, dict):
        return {k: scrub(v) for k, v in value.items() if not VOLATILE.search(k) and k not in TIMED_FILES}
    if isinstance(value, list):
        return [scrub(v) for v in value]
    return value


def digest(path: Path, root: Path) -> str:
    data = path.read_bytes()
    if path.suffix in (".json", ".jsonl", ".csv", ".html", ".md", ".txt", ".log"):  # the golden folder's own path
        text = data.decode(errors="replace")
        data = text.replace(str(root.resolve()), "<golden>").replace(str(root), "<golden>").encode()
    if path.suffix == ".json":
        data = json.dumps(scrub(json.loads(data)), sort_keys=True).encode()
    elif path.suffix == ".jsonl":
        data = "\n".join(json.dumps(scrub(json.loads(line)), sort_keys=True)
                         for line in data.decode().splitlines() if line.strip()).encode()
    elif path.suffix == ".npz":
        with zipfile.ZipFile(path) as z:
            data = b"".join(name.encode() + z.read(name) for name in sorted(z.namelist()))
    elif path.suffix == ".csv":
        rows = list(csv.reader(data.decode().splitlines()))
        keep = [i for i, name in enumerate(rows[0] if rows else []) if not VOLATILE.search(name)]
        data = "\n".join(",".join(row[i] for i in keep if i < len(row)) for row in rows).encode()
    elif path.suffix in (".html", ".md", ".txt", ".log"):
        text = data.decode()
        text = re.sub(r"\d{4}-\d\d-\d\d[ T]\d\d:\d\d(:\d\d(\.\d+)?)?(Z|[+-]\d\d:?\d\d)?", "<date>", text)
        text = re.sub(r"\b[0-9a-f]{40}\b", "<commit>", text)  # the harness commit the page names
        data = text.encode()
    return hashlib.sha256(data).hexdigest()


def main(root: str) -> int:
    base = Path(root)
    for path in sorted(p for p in base.rglob("*") if p.is_file()):
        print(digest(path, base), path.relative_to(base))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1]))

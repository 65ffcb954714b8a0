"""How the test processes were loaded: reads the lines OCTO_TEST_TIMELINE=DIR made (tests/conftest.py).

    python scripts/test_timeline.py DIR [--top N] [--write-durations tests/durations.json]

Prints each process's busy time, its idle time before the last process finished (the wall the other one lost), the
files by their summed time, and the in-process XLA compile seconds (subprocesses' compiles are not counted).
--write-durations writes each file's seconds, the order in which tests/conftest.py hands files out (longest first).
"""

from __future__ import annotations

import argparse
import collections
import json
from pathlib import Path


def read(folder: Path) -> list[dict]:
    rows = []
    for path in sorted(folder.glob("*.jsonl")):
        rows += [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if any(r["process"] != "main" for r in rows):  # under xdist the controller sees every test again, as reported
        rows = [r for r in rows if r["process"] != "main"]
    if not rows:
        raise SystemExit(f"no timeline lines in {folder}: run the tests with OCTO_TEST_TIMELINE={folder}")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--write-durations", type=Path, metavar="JSON")
    args = parser.parse_args()
    rows = read(args.folder)
    begin, finish = min(r["start"] for r in rows), max(r["end"] for r in rows)
    print(f"{len(rows)} tests, {finish - begin:.0f} s from the first start to the last end")
    by_process = collections.defaultdict(list)
    for row in rows:
        by_process[row["process"]].append(row)
    for process, own in sorted(by_process.items()):
        busy = sum(r["end"] - r["start"] for r in own)
        last = max(r["end"] for r in own)
        compile_s = sum(r["compile_s"] for r in own)
        print(f"{process}: busy {busy:.0f} s, compiling {compile_s:.0f} s in-process, done {finish - last:.0f} s "
              f"before the end, last file {own[-1]['node'].split('::')[0]}")
    files = collections.Counter()
    compiles = collections.Counter()
    for row in rows:
        name = row["node"].split("::")[0]
        files[name] += row["end"] - row["start"]
        compiles[name] += row["compile_s"]
    print(f"\n{'s':>7} {'compile':>7}  file")
    for name, seconds in files.most_common(args.top):
        print(f"{seconds:7.1f} {compiles[name]:7.1f}  {name}")
    if args.write_durations:
        ordered = {name: round(seconds, 1) for name, seconds in sorted(files.items())}
        args.write_durations.write_text(json.dumps(ordered, indent=1) + "\n")
        print(f"wrote {len(ordered)} files' seconds to {args.write_durations}")


if __name__ == "__main__":
    main()

#!/usr/bin/env bash
# EVAL.md's "## Failure early warning" section of the robosuite reference (issue 74; docs/diagnose.md), from every run
# of its primary robustness grid (results/robustness-reference, made with the failure probes on by
# scripts/robustness_reference.sh). The primary grid holds the wrist camera's cells too (camera and noise expand to
# both cameras); the wrist-camera and scene grids repeat its episodes with reliance added (same seeds and flags), so
# they are left out: diagnose refuses two runs of one name, and a repeated episode would count twice. Runs no
# episode; the grid must be finished first (an unfinished run is named in the section and its figures called interim).
#   bash scripts/early_warning_reference.sh [PRIMARY]
set -euo pipefail
cd "$(dirname "$0")/.."
PRIMARY="${1:-results/robustness-reference}"
MODEL=models/octo-reference-robosuite
PY="${PYTHON:-.venv/bin/python}"
CPU="$(lscpu 2>/dev/null | sed -n 's/^Model name: *//p' | head -1)"
SCRIPT="bash scripts/early_warning_reference.sh"
[ "$PRIMARY" != results/robustness-reference ] && SCRIPT="$SCRIPT $PRIMARY"
runs=()
for d in "$PRIMARY"/*/; do [ -f "$d/manifest.json" ] && runs+=("$d"); done
[ "${#runs[@]}" -gt 0 ] || { echo "early_warning_reference.sh: no run in $PRIMARY: run the grid first (scripts/robustness_reference.sh or scripts/reference_grids.sh)" >&2; exit 2; }
"$PY" -m harness.cli diagnose "${runs[@]}" --out "$PRIMARY/diagnose"
"$PY" -m harness.report.early_warning "${runs[@]}" --eval-md "$MODEL/EVAL.md" --command "$SCRIPT" --note \
    "Made by \`$SCRIPT\` over the ${#runs[@]} runs of the primary grid (every kind and level, both cameras). Held-out seeds 0..19, \`--readout-features-every 10 --action-consistency\`; measured on ${CPU:-an unnamed CPU}, $(nproc) cores, CPU only. Every failed episode's line: $PRIMARY/diagnose/failures.csv."

#!/usr/bin/env bash
# EVAL.md's "## Failure early warning" section of the robosuite reference (issue 74; docs/diagnose.md), from its
# robustness grids' runs, made with the failure probes on by scripts/robustness_reference.sh: every run of the primary
# grid (results/robustness-reference) and the perturbed runs of the wrist-camera grid (results/robustness-wrist; its
# nominal run repeats the primary grid's seeds). The scene grid with reliance (results/robustness-reliance) repeats
# primary cells at level 5 and is left out. Runs no episode; the grids must be finished first.
#   bash scripts/early_warning_reference.sh [PRIMARY] [WRIST]
set -euo pipefail
cd "$(dirname "$0")/.."
PRIMARY="${1:-results/robustness-reference}"
WRIST="${2:-results/robustness-wrist}"
MODEL=models/octo-reference-robosuite
PY="${PYTHON:-.venv/bin/python}"
CPU="$(lscpu 2>/dev/null | sed -n 's/^Model name: *//p' | head -1)"
SCRIPT="bash scripts/early_warning_reference.sh"
[ "$PRIMARY" != results/robustness-reference ] || [ "$WRIST" != results/robustness-wrist ] && SCRIPT="$SCRIPT $PRIMARY $WRIST"
runs=()
for d in "$PRIMARY"/*/; do [ -f "$d/manifest.json" ] && runs+=("$d"); done
for d in "$WRIST"/*/; do
  [ -f "$d/manifest.json" ] && [ "$(basename "$d")" != nominal ] && runs+=("$d")
done
[ "${#runs[@]}" -gt 0 ] || { echo "early_warning_reference.sh: no run in $PRIMARY or $WRIST: run the grids first (scripts/robustness_reference.sh, scripts/wrist_reliance_reference.sh)" >&2; exit 2; }
"$PY" -m harness.cli diagnose "${runs[@]}" --out "$PRIMARY/diagnose"
"$PY" -m harness.report.early_warning "${runs[@]}" --eval-md "$MODEL/EVAL.md" --command "$SCRIPT" --note \
    "Made by \`$SCRIPT\` over ${#runs[@]} runs: the primary grid's and the wrist-camera grid's perturbed runs (the scene grid repeats primary cells). Held-out seeds 0..19, \`--readout-features-every 1 --action-consistency\`; measured on ${CPU:-an unnamed CPU}, $(nproc) cores, CPU only. Every failed episode's line: $PRIMARY/diagnose/failures.csv."

#!/usr/bin/env bash
# EVAL.md's "## Robustness" and "## Failure early warning" sections of the robosuite reference (issue 74), from the
# primary robustness grid as kept in the repository (results/grids/robustness-reference, scripts/keep_grid_runs.py).
# Runs no episode: a fresh clone regenerates both sections, and their figures files, in a few minutes.
#   bash scripts/primary_grid_sections.sh
# Why a fresh restore and not results/robustness-reference: a kept run holds the per-step measures at the last layer
# only, while a run finished on the machine holds every layer. A grid longer than one machine's life is kept, restored
# and resumed, so some of its runs mix both, and the report refuses to average episodes of different shapes ("mixed
# models in one task"). Every run restored from the kept copy into an empty folder is cut the same way (the sections
# read the last layer only). After a grid ran, keep it first:
#   .venv/bin/python scripts/keep_grid_runs.py keep results/robustness-reference results/grids/robustness-reference
# The early-warning section reads the primary grid only: it holds the wrist camera's cells too (camera and noise
# expand to both cameras), and the wrist-camera and scene grids repeat its episodes with reliance added (same seeds and
# flags), so they are left out: diagnose refuses two runs of one name, and a repeated episode would count twice.
set -euo pipefail
cd "$(dirname "$0")/.."
KEPT=results/grids/robustness-reference
RUNS=results/robustness-reference-kept
MODEL=models/octo-reference-robosuite
PY="${PYTHON:-.venv/bin/python}"
CPU="$(lscpu 2>/dev/null | sed -n 's/^Model name: *//p' | head -1)"
SCRIPT="bash scripts/primary_grid_sections.sh"
# the command that made the runs (scripts/reference_grids.sh runs it, resumably)
GRID="bash scripts/robustness_reference.sh Lift,Stack,PickPlaceCan camera,lighting,texture,distractors,init-state,noise,language 0,1,3,5 20"
FLAGS="octo-harness robustness --model $MODEL --task Lift,Stack,PickPlaceCan --perturb camera,lighting,texture,distractors,init-state,noise,language --levels 0,1,3,5 --episodes 20 --seed 0 --fast-render --png-every 0 --no-video --readout-features-every 10 --action-consistency"
MACHINE="sections rendered on ${CPU:-an unnamed CPU}, $(nproc) cores"
rm -rf "$RUNS"
"$PY" scripts/keep_grid_runs.py restore "$KEPT" "$RUNS"
runs=()
for d in "$RUNS"/*/; do [ -f "$d/manifest.json" ] && runs+=("$d"); done
[ "${#runs[@]}" -gt 0 ] || { echo "primary_grid_sections.sh: no kept run in $KEPT: run scripts/reference_grids.sh first" >&2; exit 2; }
"$PY" -m harness.cli report "${runs[@]}" --out "$RUNS/report"
"$PY" -m harness.report.robustness "${runs[@]}" --eval-md "$MODEL/EVAL.md" --section Robustness --command "$SCRIPT" \
    --note "Runs made by \`$GRID\`: \`$FLAGS\` (held-out seeds 0..19, each task at its own step limit, masks on; kinds and levels: docs/perturbations.md), kept in $KEPT; $MACHINE, from a fresh restore of them. Target lift and nuisance mass: primary camera, last layer, mean over each episode's steps."
"$PY" -m harness.cli diagnose "${runs[@]}" --out "$RUNS/diagnose"
"$PY" -m harness.report.early_warning "${runs[@]}" --eval-md "$MODEL/EVAL.md" --command "$SCRIPT" --note \
    "Runs made by \`$GRID\` (${#runs[@]} runs: every kind and level, both cameras; held-out seeds 0..19, \`--readout-features-every 10 --action-consistency\`), kept in $KEPT; $MACHINE, CPU only. Every failed episode's line: $RUNS/diagnose/failures.csv."
# the figures docs/perturbations.md shows
for png in "$RUNS"/report/plots/robustness_*.png; do
    [ -f "$png" ] && cp "$png" "docs/robustness_reference_$(basename "$png" .png | sed 's/^robustness_//').png"
done

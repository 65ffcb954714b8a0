#!/usr/bin/env bash
# Every robustness grid of the robosuite reference, one after the other, then EVAL.md's sections from them (issue 74):
#   1. the wrist-camera grid with reliance (scripts/wrist_reliance_reference.sh: "## Robustness of the wrist camera",
#      "## Reliance");
#   2. the scene grid with reliance (scripts/scene_reliance_reference.sh: "## Robustness with reliance"), its nominal
#      run copied from the wrist grid's first (the same command, seeds and flags: 60 episodes saved);
#   3. the primary grid (scripts/robustness_reference.sh: 7 kinds x levels 0,1,3,5 x Lift, Stack, PickPlaceCan, 20
#      seeds; "## Robustness");
#   4. "## Robustness" and "## Failure early warning" (scripts/primary_grid_sections.sh), from the primary grid kept
#      in results/grids/robustness-reference and restored into a fresh folder (every run cut the same way).
# Every run records the failure probes. Each step resumes where a killed one stopped: re-run the same command.
# Many hours on 2 cores (about 2,160 episodes: 1,680 in the primary grid), longer than a machine lasts here: the runs
# kept in results/grids/ (scripts/keep_grid_runs.py) are restored first, so a new machine runs only what they lack.
# Keep what a machine finished before it goes, from the same checkout path (the runs record the model's path):
#   for g in reference wrist reliance; do .venv/bin/python scripts/keep_grid_runs.py keep \
#       results/robustness-$g results/grids/robustness-$g; done
#   bash scripts/reference_grids.sh [WORKERS]
set -euo pipefail
cd "$(dirname "$0")/.."
WORKERS="${1:-2}"
PY="${PYTHON:-.venv/bin/python}"
for g in reference wrist reliance; do
  "$PY" scripts/keep_grid_runs.py restore "results/grids/robustness-$g" "results/robustness-$g"
done
bash scripts/wrist_reliance_reference.sh "$WORKERS"
if [ ! -e results/robustness-reliance/nominal ] && [ -f results/robustness-wrist/nominal/manifest.json ]; then
  mkdir -p results/robustness-reliance
  cp -a results/robustness-wrist/nominal results/robustness-reliance/nominal
fi
bash scripts/scene_reliance_reference.sh "$WORKERS"
# the primary grid last; its runs are what the early-warning section reads
RUN_ONLY=1 bash scripts/robustness_reference.sh Lift,Stack,PickPlaceCan camera,lighting,texture,distractors,init-state,noise,language \
    0,1,3,5 20 results/robustness-reference "$WORKERS"
"$PY" scripts/keep_grid_runs.py keep results/robustness-reference results/grids/robustness-reference
bash scripts/primary_grid_sections.sh

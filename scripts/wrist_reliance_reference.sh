#!/usr/bin/env bash
# The wrist camera's cells of the reference robustness grid (issue 43: camera@image_wrist at levels 1, 3, 5 on Lift,
# Stack and PickPlaceCan, 20 held-out seeds, against this machine's own nominal run) with region reliance at every 4th
# step (issue 45: which of nuisance reliance and nuisance attention predicts failure), into results/robustness-wrist.
# Writes EVAL.md's "## Robustness of the wrist camera" and "## Reliance" sections (other sections stay).
#   bash scripts/wrist_reliance_reference.sh [WORKERS] [LEVELS]
# LEVELS defaults to 0,1,3,5; a grid folder grows level by level, and the same command resumes a killed grid.
set -euo pipefail
cd "$(dirname "$0")/.."
RELIANCE=4 SECTION="Robustness of the wrist camera" exec bash scripts/robustness_reference.sh Lift,Stack,PickPlaceCan \
    camera@image_wrist "${2:-0,1,3,5}" 20 results/robustness-wrist "${1:-2}"

#!/usr/bin/env bash
# The scene cells of the reference robustness grid that break or nearly break the policy (issue 45 item 5: texture,
# noise on the primary camera, lighting and distractors at level 5; in the full grid, texture and noise 5 broke Lift,
# distractors 5 cost it 8 of 20) on Lift, Stack and PickPlaceCan, 20 held-out seeds, against this machine's own
# nominal run, with region reliance at every 4th step (which of nuisance reliance and nuisance attention predicts
# failure), into results/robustness-reliance. Writes EVAL.md's "## Robustness with reliance" and "## Reliance"
# sections (other sections stay). The wrist camera's cells are scripts/wrist_reliance_reference.sh.
#   bash scripts/scene_reliance_reference.sh [WORKERS]
# The nominal run is the same command, seeds and flags as the wrist grid's: copying results/robustness-wrist/nominal
# into results/robustness-reliance/ first saves its 60 episodes (the run store resumes it as finished). The same
# command resumes a killed grid.
set -euo pipefail
cd "$(dirname "$0")/.."
RELIANCE=4 SECTION="Robustness with reliance" exec bash scripts/robustness_reference.sh Lift,Stack,PickPlaceCan \
    texture,noise@image_primary,lighting,distractors 0,5 20 results/robustness-reliance "${1:-2}"

#!/usr/bin/env bash
# The second demo: the LIBERO-Object reference policy (models/octo-reference-libero-object) on libero_object/2 ("pick
# up the salad dressing and place it in the basket"), stored initial state 0 of the published protocol, where it
# succeeds in about 90 steps (it succeeds on 19 of that task's first 20 states: the model card's EVAL.md),
# headless, writing attention overlays on both cameras (every 10th step, every layer), an MP4 with one row per camera
# and the run folder under results/runs/. Makes .venv and LIBERO's .venv-libero first when missing. Extra arguments
# go to `octo-harness run` and override these (e.g. --task libero_object/0 --seed 3 for a task it fails, or
# --instruction "..." to tell the scene another object).
source "$(dirname "$0")/_bootstrap.sh"
bash "$(dirname "$0")/setup_libero.sh"
exec .venv/bin/octo-harness run --task libero_object/2 --episodes 1 --seed 0 --fast-render --png-every 10 \
    --model models/octo-reference-libero-object "$@"

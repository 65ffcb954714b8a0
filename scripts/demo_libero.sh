#!/usr/bin/env bash
# The second demo: the LIBERO-Object reference policy (models/octo-reference-libero-object) on libero_object/0 ("pick
# up the alphabet soup ..."), stored initial state 1 of the published protocol, where it grasps the alphabet soup (it
# does not lift it: see the model card's evaluation),
# headless, writing attention overlays on both cameras (every 10th step, every layer), an MP4 with one row per camera
# and the run folder under results/runs/. Makes .venv and LIBERO's .venv-libero first when missing. Extra arguments
# go to `octo-harness run` and override these (e.g. --task libero_object/7 --seed 3, or --instruction "...").
source "$(dirname "$0")/_bootstrap.sh"
bash "$(dirname "$0")/setup_libero.sh"
exec .venv/bin/octo-harness run --task libero_object/0 --episodes 1 --seed 1 --fast-render --png-every 10 \
    --model models/octo-reference-libero-object "$@"

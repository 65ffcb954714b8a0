#!/usr/bin/env bash
# The main job: a headless closed-loop rollout of the reference policy (models/octo-reference-robosuite) on Lift,
# writing attention overlays (every step, every layer), an MP4 and the run folder under results/runs/.
# Seed 1 is an evaluation seed on which the policy lifts the cube (~30 steps). Extra arguments are passed to
# `octo-harness run` and override these (e.g. --model hf://rail-berkeley/octo-small-1.5 --seed 0).
source "$(dirname "$0")/_bootstrap.sh"
exec .venv/bin/octo-harness run --task Lift --episodes 1 --seed 1 --max-steps 100 --fast-render \
    --model models/octo-reference-robosuite "$@"

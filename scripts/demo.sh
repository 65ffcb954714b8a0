#!/usr/bin/env bash
# The main job: a headless closed-loop rollout that writes attention overlays and an MP4.
# Extra arguments are passed to `octo-harness run` (e.g. --model hf://rail-berkeley/octo-small-1.5).
source "$(dirname "$0")/_bootstrap.sh"
exec .venv/bin/octo-harness run --task Lift --episodes 1 --max-steps 20 --model random:octo-small-1.5 "$@"

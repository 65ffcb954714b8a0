#!/usr/bin/env bash
# Evaluate the reference policy the way EVAL.md and the README report it: 50 episodes per task on the held-out
# seeds 0..49, each task at its own step limit (Lift 300, Stack 400, PickPlaceCan 400), fast render, no PNG/MP4,
# two env workers (same episodes as a sequential run), then the table with Wilson intervals and target lift.
#   bash scripts/evaluate_reference.sh [MODEL] [OUT] [EPISODES]
# The runs are resumable: re-running the same command finishes what a killed evaluation left.
set -euo pipefail
cd "$(dirname "$0")/.."
MODEL="${1:-models/octo-reference-robosuite}"
OUT="${2:-results/reference-eval}"
EPISODES="${3:-50}"
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
runs=()
for task in Lift Stack PickPlaceCan; do
    .venv/bin/octo-harness run --model "$MODEL" --task "$task" --episodes "$EPISODES" --seed 0 --fast-render \
        --png-every 0 --no-video --workers 2 --out "$OUT" --run-name "$task"
    runs+=("$OUT/$task")
done
step="$(find "$MODEL" -mindepth 1 -maxdepth 1 -type d -regex '.*/[0-9]+' -printf '%f\n' | sort -n | tail -1)"
how="bash scripts/evaluate_reference.sh"  # the command as EVAL.md gives it: with the model when it is not the default
[ "$MODEL" = models/octo-reference-robosuite ] || how="$how $MODEL"
.venv/bin/python -m reference_policies.evaluate "${runs[@]}" --out "$MODEL" --command "$how" --note \
    "Checkpoint step $step. Made by \`$how\`: per task \`octo-harness run --model $MODEL --task <task> --episodes $EPISODES --seed 0 --fast-render --png-every 0 --no-video --workers 2\` (held-out seeds 0..$((EPISODES - 1)), each task at its own step limit: Lift 300, Stack 400, PickPlaceCan 400; robosuite action space and statistics from harness.toml; temporal ensembling; masks on)."

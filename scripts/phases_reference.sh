#!/usr/bin/env bash
# Task phases and position-against-content controls on the committed reference policy: the runs behind
# docs/phases-and-position.md and the "Phases and position" section of models/octo-reference-robosuite/EVAL.md.
#   Lift, Stack, PickPlaceCan: 10 episodes each on held-out seeds 0..9 (each task at its own step limit), masks on
#   (target, robot, gripper, arm, goal), phases recorded, attention controls (blank, mirror) every 5th step,
#   the policy's inputs recorded (the report draws flagged patches over them).
# Then the HTML report (Phases and Position sections, tables/*.csv) and the Markdown tables for the docs.
#   bash scripts/phases_reference.sh [OUT]        (resumable: re-running finishes what a killed one left)
#   PY=/path/to/python bash scripts/phases_reference.sh    (another interpreter than .venv/bin/python)
set -euo pipefail
cd "$(dirname "$0")/.."
MODEL="${MODEL:-models/octo-reference-robosuite}"
OUT="${1:-results/runs/phases}"
PY="${PY:-.venv/bin/python}"
EPISODES="${EPISODES:-10}"
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
runs=()
for task in Lift Stack PickPlaceCan; do
    "$PY" -m harness.cli run --model "$MODEL" --task "$task" --episodes "$EPISODES" --seed 0 \
        --attention-controls blank,mirror --controls-every 5 --record-inputs \
        --fast-render --png-every 0 --no-video --out "$OUT" --run-name "phases_$task"
    runs+=("$OUT/phases_$task")
done
"$PY" -m harness.cli report "${runs[@]}" --out "$OUT/report"
# EVAL.md's "## Phases and position" section (phase tables, then position tables), from $MODEL/figures/phases-and-position.json
note="Lift, Stack and PickPlaceCan, $EPISODES episodes each on held-out seeds 0..$((EPISODES - 1)), each task at its own step limit."
note+=" Masks on, \`--attention-controls blank,mirror --controls-every 5\`. Definitions: [docs/phases-and-position.md](../../docs/phases-and-position.md)."
note+=" The p-values are uncorrected."
"$PY" -m harness.report.phases "${runs[@]}" --command "bash scripts/phases_reference.sh" --eval-md "$MODEL/EVAL.md" \
    --note "$note" > "$OUT/phases.md"
# the figures docs/phases-and-position.md shows
for task in Lift Stack PickPlaceCan; do
    lower=$(echo "$task" | tr '[:upper:]' '[:lower:]')
    cp "$OUT/report/plots/position_${lower}_phases_${task}.png" "docs/phases_position_${lower}.png"
    cp "$OUT/report/plots/phase_events_${lower}_phases_${task}.png" "docs/phases_events_${lower}.png"
done
echo "report: $OUT/report/report.html; section: $MODEL/EVAL.md (also $OUT/phases.md)"

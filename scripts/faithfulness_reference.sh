#!/usr/bin/env bash
# Is the reference policy's attention telling the truth? The runs behind EVAL.md's "Faithfulness" section.
#   Open loop: 6 episodes per task (seeds 100..105, at most 120 steps), faithfulness every 10th step, every method;
#   Lift and Stack again with occlusion.
#   Closed loop: 30 episodes per task on the held-out seeds 0..29 (Lift at most 150 steps, Stack 250, PickPlaceCan
#   at its own limit, 400; PickPlaceCan with 2 env workers, the same episodes as sequential), plain and with
#   --intervene mask-top:4:attention:2 / mask-top:4:saliency / mask-random:4 / mask-all (4 of each camera's 16 patches).
# Then the Markdown tables (python -m harness.report.faithfulness) and an HTML report with the Faithfulness section.
#   bash scripts/faithfulness_reference.sh [OUT]        (resumable: re-running finishes what a killed one left)
set -euo pipefail
cd "$(dirname "$0")/.."
MODEL="${MODEL:-models/octo-reference-robosuite-64px}"  # the policy the published results were measured on; MODEL=... for another
OUT="${1:-results/runs/faith}"
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
run() { .venv/bin/octo-harness run --model "$MODEL" --fast-render --png-every 0 --no-video --out "$OUT" "$@"; }
open=()
for task in Lift Stack PickPlaceCan; do
    run --task "$task" --episodes 6 --seed 100 --max-steps 120 --faithfulness-every 10 --run-name "open_$task"
    open+=("$OUT/open_$task")
done
for task in Lift Stack; do  # the same episodes with occlusion, the reference a faithful map is measured against
    run --task "$task" --episodes 6 --seed 100 --max-steps 120 --faithfulness-every 10 \
        --attribution attention:2,saliency,occlusion --run-name "occ_$task"
    open+=("$OUT/occ_$task")
done
closed=()
for spec in "Lift 150 1" "Stack 250 1" "PickPlaceCan 400 2"; do
    set -- $spec
    task=$1 steps=$2 workers=$3
    for arm in plain "top-attn2 mask-top:4:attention:2" "top-saliency mask-top:4:saliency" "random mask-random:4" "all mask-all"; do
        set -- $arm
        name=$1 intervention=${2:-}
        run --task "$task" --episodes 30 --seed 0 --max-steps "$steps" --workers "$workers" --run-name "${task}_$name" \
            ${intervention:+--intervene "$intervention"}
        closed+=("$OUT/${task}_$name")
    done
done
# EVAL.md's "## Faithfulness" section, rendered from its figures file ($MODEL/figures/faithfulness.json)
.venv/bin/python -m harness.report.faithfulness "${open[@]}" "${closed[@]}" --command "bash scripts/faithfulness_reference.sh" \
    --figure docs/faithfulness_reference.png --eval-md "$MODEL/EVAL.md"
.venv/bin/octo-harness report "${open[@]}" --out "$OUT/report_open"

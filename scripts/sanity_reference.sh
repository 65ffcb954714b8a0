#!/usr/bin/env bash
# Sanity checks of the attribution methods and of the faithfulness metric on the reference policy: the numbers
# behind models/octo-reference-robosuite/EVAL.md "Sanity checks" and docs/faithfulness-sanity.md.
#   1. Open loop, three fills: 2 episodes per task (seeds 100, 101, at most 100 steps), faithfulness every 20th
#      step (Lift, whose episodes end in ~30 steps: 4 episodes, every 10th step), every method plus occlusion, with --faithfulness-fill mean and impute (then blur, last: the least
#      needed), the same episodes (the faithfulness probe does not change actions), inputs recorded.
#   2. `octo-harness sanity` on the recorded inputs of the Lift and Stack mean-fill runs (every 40th step), pooled: model-parameter randomisation (cascading and per block) and the single-patch / additivity
#      measures per camera and fill -> $OUT/sanity.md.
#   3. Closed loop per camera, Lift seeds 300..305 (at most 150 steps): plain, mask-all@image_wrist,
#      mask-all@image_primary, mask-top:4:attention:2@image_wrist against mask-random:4@image_wrist (a quarter of
#      the wrist's 16 patches).
# Then the Markdown tables (python -m harness.report.faithfulness -> $OUT/faithfulness.md) and the HTML report.
# The compute is kept small for a shared 2-core CPU; raise --episodes for tighter intervals.
#   bash scripts/sanity_reference.sh [OUT]        (resumable: re-running finishes what a killed one left)
set -euo pipefail
cd "$(dirname "$0")/.."
MODEL="${MODEL:-models/octo-reference-robosuite}"
OUT="${1:-results/runs/sanity}"
PY="${PY:-.venv/bin/python}"
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
run() { "$PY" -m harness.cli run --model "$MODEL" --fast-render --png-every 0 --no-video --out "$OUT" "$@"; }
openrun() {  # FILL TASK: the open-loop faithfulness run of one task with one fill (Lift ends in ~30 steps: 4
             # episodes, every 10th step; the others 2 episodes, every 20th)
    if [ "$2" = Lift ]; then set -- "$1" "$2" 4 10; else set -- "$1" "$2" 2 20; fi
    run --task "$2" --episodes "$3" --seed 100 --max-steps 100 --faithfulness-every "$4" --faithfulness-fill "$1" \
        --attribution attention,rollout,grad-attention,saliency,occlusion --record-inputs --run-name "open_$1_$2"
}
# most needed first (the compute is shared): Lift with both fills, the closed loop, the sanity checks, Stack;
# then PickPlaceCan and the blur fill
openrun mean Lift
openrun impute Lift
closed=()
for arm in "plain" "all-wrist mask-all@image_wrist" "all-primary mask-all@image_primary" \
           "top-wrist mask-top:4:attention:2@image_wrist" "random-wrist mask-random:4@image_wrist"; do
    set -- $arm
    name=$1 intervention=${2:-}
    run --task Lift --episodes 6 --seed 300 --max-steps 150 --run-name "Lift_$name" ${intervention:+--intervene "$intervention"}
    closed+=("$OUT/Lift_$name")
done
openrun mean Stack
"$PY" -m harness.cli sanity "$OUT"/open_mean_{Lift,Stack} --every 40 --additivity --out "$OUT/sanity" > "$OUT/sanity.md"
openrun impute Stack
openrun mean PickPlaceCan
openrun impute PickPlaceCan
for task in Lift Stack PickPlaceCan; do openrun blur "$task"; done
open=("$OUT"/open_{mean,impute,blur}_{Lift,Stack,PickPlaceCan})
"$PY" -m harness.report.faithfulness "${open[@]}" "${closed[@]}" --command "bash scripts/sanity_reference.sh" > "$OUT/faithfulness.md"
"$PY" -m harness.cli report "${open[@]}" "${closed[@]}" --out "$OUT/report"

#!/usr/bin/env bash
# Evaluate the LIBERO-Object reference policy as its EVAL.md reports it (docs/libero-reference.md):
#   1. the published protocol: every LIBERO-Object task from stored initial states 0..STATES-1, step limit 280, masks
#      on (named-object attention) -> EVAL.md's success table (Wilson intervals, average over tasks);
#   2. language, from states 0..PROBE-1, masks off: each scene told another task's instruction (an object that scene
#      also holds), the first paraphrase of its own, and a nonsense instruction -> which object was picked
#      (EVAL.md "Language grounding", with the named-object attention of run 1);
#   3. closed loop, from states 0..PROBE-1: mask-top:TOPK:attention:LAYER against mask-random:TOPK, paired by
#      initial state (octo-harness compare) -> EVAL.md "Closed loop".
#   bash scripts/evaluate_libero_reference.sh [STATES] [PROBE] [OUT]      (the published protocol: STATES=50)
# LANGUAGE="swap paraphrase nonsense" (default: all three) picks the probes of stage 2; INTERVENTIONS=0 skips stage 3;
# MODEL=DIR evaluates another checkpoint (default: the committed one).
# Runs of stages 2 and 3 are small, so they go in two parallel streams of one env worker each. Resumable: re-running
# the same command finishes what a killed evaluation left.
set -euo pipefail
cd "$(dirname "$0")/.."
STATES="${1:-50}"
PROBE="${2:-10}"
OUT="${3:-results/libero-reference-eval}"
MODEL="${MODEL:-models/octo-reference-libero-object}"  # MODEL=DIR evaluates a candidate before it is committed
LANGUAGE="${LANGUAGE:-swap paraphrase nonsense}"
INTERVENTIONS="${INTERVENTIONS:-1}"
TOPK="${TOPK:-8}"
LAYER="${LAYER:-3}"
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
PY=.venv/bin/python
common=(--model "$MODEL" --seed 0 --fast-render --png-every 0 --no-video --out "$OUT")
"$PY" -m harness.cli run "${common[@]}" --workers 2 --task libero_object --episodes "$STATES" --run-name published

# stage 2: (run name, task, instruction) lines, then two streams
nonsense="$("$PY" -m reference_policies.libero_eval nonsense)"
plan="$(mktemp)"
trap 'rm -f "$plan"' EXIT
if [[ " $LANGUAGE " == *" swap "* ]]; then
    "$PY" -m reference_policies.libero_eval swaps | while IFS=$'\t' read -r task instruction; do
        printf 'swap_%s\t%s\t%s\n' "${task#libero_object/}" "$task" "$instruction"
    done >> "$plan"
fi
for index in 0 1 2 3 4 5 6 7 8 9; do
    if [[ " $LANGUAGE " == *" paraphrase "* ]]; then
        paraphrase="$("$PY" -c "import envs; print(envs.get_task('libero_object/$index').paraphrases[0])")"
        printf 'paraphrase_%s\tlibero_object/%s\t%s\n' "$index" "$index" "$paraphrase" >> "$plan"
    fi
    if [[ " $LANGUAGE " == *" nonsense "* ]]; then
        printf 'nonsense_%s\tlibero_object/%s\t%s\n' "$index" "$index" "$nonsense" >> "$plan"
    fi
done
stream() {  # every other line of the plan, from line $1
    awk -v s="$1" 'NR % 2 == s' "$plan" | while IFS=$'\t' read -r name task instruction; do
        "$PY" -m harness.cli run "${common[@]}" --no-masks --task "$task" --episodes "$PROBE" --run-name "$name" \
            --instruction "$instruction" </dev/null
    done
}
stream 0 & first=$!
stream 1
wait "$first"
language=()
while IFS=$'\t' read -r name _; do language+=("$OUT/$name"); done < "$plan"

# stage 3: the two interventions side by side
if [ "$INTERVENTIONS" != 0 ]; then
    "$PY" -m harness.cli run "${common[@]}" --no-masks --task libero_object --episodes "$PROBE" --run-name mask_top \
        --intervene "mask-top:$TOPK:attention:$LAYER" & top=$!
    "$PY" -m harness.cli run "${common[@]}" --no-masks --task libero_object --episodes "$PROBE" --run-name mask_random \
        --intervene "mask-random:$TOPK"
    wait "$top"
fi

step="$(find "$MODEL" -mindepth 1 -maxdepth 1 -type d -regex '.*/[0-9]+' -printf '%f\n' | sort -n | tail -1)"
how="bash scripts/evaluate_libero_reference.sh $STATES $PROBE"  # the command as EVAL.md gives it: it names MODEL when
[ "$MODEL" = models/octo-reference-libero-object ] || how="MODEL=$MODEL $how"  # another checkpoint was evaluated
"$PY" -m reference_policies.evaluate "$OUT/published" --out "$MODEL" \
    --command "$how" --note \
    "Checkpoint step $step. Made by \`$how\`: \`octo-harness run --model $MODEL --task libero_object --episodes $STATES --seed 0 --fast-render --png-every 0 --no-video --workers 2\` (LIBERO-Object's published protocol: stored initial states 0..$((STATES - 1)) of each task, 10 settle steps, step limit 280; libero action space, rot180 images and cameras from harness.toml; masks on)."
"$PY" -m harness.report.grounding "$OUT/published" "${language[@]}" --eval-md "$MODEL/EVAL.md" \
    --command "LANGUAGE=\"$LANGUAGE\" $how" --note \
    "Made by \`LANGUAGE=\"$LANGUAGE\" $how\`: own instructions from the published run (states 0..$((STATES - 1))); the probes $LANGUAGE (nonsense: \`$nonsense\`) from states 0..$((PROBE - 1)), masks off (the picked object is read from the simulator at the episode's end: in the basket, else held)."
if [ "$INTERVENTIONS" != 0 ]; then
    "$PY" -m harness.cli compare "$OUT/mask_random" "$OUT/mask_top" --no-frames --out "$OUT/compare_mask_top" || true
    "$PY" -m reference_policies.libero_eval closed-loop "$OUT/mask_random" "$OUT/mask_top" \
        --eval-md "$MODEL/EVAL.md" --command "$how" --note "Made by \`$how\`: \`--intervene mask-top:$TOPK:attention:$LAYER\` against \`--intervene mask-random:$TOPK\`, states 0..$((PROBE - 1)) of every task, masks off."
fi
"$PY" -m harness.cli report "$OUT/published" "${language[@]}" --out "$OUT/report"

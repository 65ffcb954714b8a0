#!/usr/bin/env bash
# Evaluate the LIBERO-Object reference policy as its EVAL.md reports it (docs/libero.md):
#   1. the published protocol: every LIBERO-Object task from stored initial states SEED..SEED+STATES-1, step limit 280,
#      masks on (named-object attention), -> EVAL.md's success table (Wilson intervals) and target lift;
#   2. language: each scene told another task's instruction (an object that scene holds), a paraphrase of its own, and
#      a nonsense instruction, from states 0..PROBE_STATES-1 -> which object was picked (EVAL.md "Language grounding");
#   3. closed loop: mask-top:K:attention:L against mask-random:K from the same states, paired by initial state.
#   bash scripts/evaluate_libero_reference.sh [STATES] [PROBE_STATES] [OUT]      (published: STATES=50)
# Resumable: re-running the same command finishes what a killed evaluation left.
set -euo pipefail
cd "$(dirname "$0")/.."
STATES="${1:-50}"
PROBE="${2:-10}"
OUT="${3:-results/libero-reference-eval}"
MODEL=models/octo-reference-libero-object
TOPK="${TOPK:-8}"
LAYER="${LAYER:-3}"
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
PY=.venv/bin/python
common=(--model "$MODEL" --seed 0 --fast-render --png-every 0 --no-video --workers 2 --out "$OUT")
"$PY" -m harness.cli run "${common[@]}" --task libero_object --episodes "$STATES" --run-name published
language=()
while IFS=$'\t' read -r task instruction; do
    index="${task#libero_object/}"
    "$PY" -m harness.cli run "${common[@]}" --no-masks --task "$task" --episodes "$PROBE" --run-name "swap_$index" \
        --instruction "$instruction"
    language+=("$OUT/swap_$index")
done < <("$PY" -m harness.reference.libero_eval swaps)
nonsense="$("$PY" -m harness.reference.libero_eval nonsense)"
for index in 0 1 2 3 4 5 6 7 8 9; do
    paraphrase="$("$PY" -c "import envs; print(envs.get_task('libero_object/$index').paraphrases[0])")"
    "$PY" -m harness.cli run "${common[@]}" --no-masks --task "libero_object/$index" --episodes "$PROBE" \
        --run-name "paraphrase_$index" --instruction "$paraphrase"
    "$PY" -m harness.cli run "${common[@]}" --no-masks --task "libero_object/$index" --episodes "$PROBE" \
        --run-name "nonsense_$index" --instruction "$nonsense"
    language+=("$OUT/paraphrase_$index" "$OUT/nonsense_$index")
done
"$PY" -m harness.cli run "${common[@]}" --task libero_object --episodes "$PROBE" --run-name "mask_top" \
    --intervene "mask-top:$TOPK:attention:$LAYER"
"$PY" -m harness.cli run "${common[@]}" --task libero_object --episodes "$PROBE" --run-name "mask_random" \
    --intervene "mask-random:$TOPK"
step="$(find "$MODEL" -mindepth 1 -maxdepth 1 -type d -regex '.*/[0-9]+' -printf '%f\n' | sort -n | tail -1)"
"$PY" -m harness.reference.evaluate "$OUT/published" --out "$MODEL" --note \
    "Checkpoint step $step. Made by \`bash scripts/evaluate_libero_reference.sh $STATES $PROBE\`: \`octo-harness run --model $MODEL --task libero_object --episodes $STATES --seed 0 --fast-render --png-every 0 --no-video --workers 2\` (LIBERO-Object's published protocol: stored initial states 0..$((STATES - 1)) of each task, 10 settle steps, step limit 280; libero action space, rot180 images and cameras from harness.toml; masks on)."
"$PY" -m harness.report.grounding "$OUT/published" "${language[@]}" --eval-md "$MODEL/EVAL.md" --note \
    "Made by \`bash scripts/evaluate_libero_reference.sh $STATES $PROBE\`: own instructions from the published run (states 0..$((STATES - 1))); swaps, paraphrases and the nonsense instruction (\`$nonsense\`) from states 0..$((PROBE - 1)), masks off (the picked object is read from the simulator at the episode's end)."
"$PY" -m harness.cli compare "$OUT/mask_random" "$OUT/mask_top" --out "$OUT/compare_mask_top" || true
"$PY" -m harness.cli report "$OUT/published" "${language[@]}" --out "$OUT/report"

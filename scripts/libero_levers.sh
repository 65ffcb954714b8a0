#!/usr/bin/env bash
# Issue 46's table of levers (docs/history/libero-reference.md "Grasp probe"): probe each LIBERO-Object checkpoint on stored
# states 0-1 of every task (20 episodes, the published loop, as the evaluation runs it), then print one markdown
# table in the order given. LABEL=expert probes the state-based expert (the yardstick).
#   bash scripts/libero_levers.sh expert first=models/octo-reference-libero-object-first second=models/octo-reference-libero-object
# Each probe is written to $OUT/LABEL.json (default data/libero_levers) and reused while its checkpoint (config,
# statistics, harness.toml, weights), states, tasks and step limit are the same, so re-running only probes what changed.
# LANGUAGE=swap tells each scene its swap instead (the evaluation's: the next task whose named object it holds) and
# writes $OUT/LABEL_swap.json; its success is the named object, alone, in the basket.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "$#" -eq 0 ]; then
    echo "usage: bash scripts/libero_levers.sh expert|LABEL=CHECKPOINT_DIR ..." >&2
    exit 2
fi
LANGUAGE="${LANGUAGE:-own}"
case "$LANGUAGE" in
    own) suffix="" ;;
    swap) suffix="_swap" ;;
    *) echo "libero_levers: LANGUAGE=$LANGUAGE: use own or swap" >&2; exit 2 ;;
esac
source scripts/_bootstrap.sh
bash scripts/setup_libero.sh
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
OUT="${OUT:-data/libero_levers}"
STATES="${STATES:-0,1}"
table=()
for spec in "$@"; do
    label="${spec%%=*}"
    if [ "$spec" = expert ]; then
        who=(--expert)
    elif [ "$label" != "$spec" ] && [ -n "$label" ]; then
        who=(--model "${spec#*=}")
    else
        echo "libero_levers: $spec: give LABEL=CHECKPOINT_DIR or expert" >&2
        exit 2
    fi
    .venv/bin/python -m reference_policies.libero_probe "${who[@]}" --states "$STATES" --workers "${WORKERS:-2}" \
        --language "$LANGUAGE" --out "$OUT/$label$suffix.json" > /dev/null
    table+=("$label$suffix=$OUT/$label$suffix.json")
done
.venv/bin/python -m reference_policies.libero_probe --table "${table[@]}"

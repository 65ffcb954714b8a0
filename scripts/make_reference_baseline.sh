#!/usr/bin/env bash
# Regenerate the committed baseline of the reference policy: results/baselines/reference-lift
# (8 Lift episodes on evaluation seeds 0..7, at most 80 steps, fast render, no PNG/MP4, policy inputs recorded;
# arrays and inputs of the first 20 steps kept for `octo-harness replay`), made from a fresh run of
# models/octo-reference-robosuite. Run it again whenever the reference checkpoint changes (the baseline gate,
# tests/gate/test_committed_baseline.py, checks the model fingerprint and says so).
#   bash scripts/make_reference_baseline.sh [MODEL] [NAME] [MAX_STEPS]
set -euo pipefail
cd "$(dirname "$0")/.."
MODEL="${1:-models/octo-reference-robosuite}"
NAME="${2:-reference-lift}"
MAX_STEPS="${3:-80}"
RUNS="$(mktemp -d)"
trap 'rm -rf "$RUNS"' EXIT
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
.venv/bin/octo-harness run --task Lift --episodes 8 --seed 0 --max-steps "$MAX_STEPS" --model "$MODEL" \
    --fast-render --png-every 0 --no-video --record-inputs --out "$RUNS" --run-name "$NAME"
.venv/bin/python scripts/make_baseline.py "$RUNS/$NAME" "results/baselines/$NAME"

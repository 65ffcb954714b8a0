#!/usr/bin/env bash
# Robustness grid of the reference policy (docs/perturbations.md, EVAL.md): kinds x levels x tasks on held-out seeds
# (seed 0 upward, as scripts/evaluate_reference.sh), fast render, no PNG/MP4, masks on, then the report with its
# Robustness section (every number in OUT/report/tables/robustness_*.csv).
#   bash scripts/robustness_reference.sh [TASKS] [KINDS] [LEVELS] [EPISODES] [OUT] [WORKERS]
# The full grid of issue 27 is the default (20 episodes x levels 0,1,3,5 x every kind x Lift, Stack, PickPlaceCan);
# `camera` and `noise` expand to one condition per camera the policy reads (camera@image_primary, camera@image_wrist,
# noise@image_primary, noise@image_wrist: issue 43), so the default grid moves the wrist camera too. A grid folder
# made before keeps its run names (camera-3 is camera@image_primary:3) and gains only the new cells on re-running.
# the reduced grid in EVAL.md was: bash scripts/robustness_reference.sh Lift <every kind> 0,3,5 5
# (run first with camera,lighting,distractors, then extended with the other kinds: a grid folder grows)
# Resumable: re-running the same command finishes what a killed grid left.
# Every run records the two failure probes (issue 74: --readout-features-every 10 --action-consistency) for
# `octo-harness diagnose` and EVAL.md's "## Failure early warning" section (scripts/primary_grid_sections.sh).
# RUN_ONLY=1 runs the grid and writes no report or section (scripts/reference_grids.sh: the primary grid's sections
# are rendered from its kept copy by scripts/primary_grid_sections.sh, since a grid resumed across machines mixes kept
# runs, cut to the last layer, with full ones).
# RELIANCE=N adds --reliance-every N to every run (issue 45) and writes EVAL.md's "## Reliance" section from the
# nominal run; SECTION=TITLE writes the grid's table under "## TITLE" instead of "## Robustness" (a second grid, as
# scripts/wrist_reliance_reference.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
TASKS="${1:-Lift,Stack,PickPlaceCan}"
KINDS="${2:-camera,lighting,texture,distractors,init-state,noise,language}"
LEVELS="${3:-0,1,3,5}"
EPISODES="${4:-20}"
OUT="${5:-results/robustness-reference}"
WORKERS="${6:-}"
RELIANCE="${RELIANCE:-}"
SECTION="${SECTION:-Robustness}"
CPU="$(lscpu 2>/dev/null | sed -n 's/^Model name: *//p' | head -1)"
NOTE="${NOTE:-Measured on ${CPU:-an unnamed CPU}, $(nproc) cores, CPU only.}"
MODEL=models/octo-reference-robosuite
PROBES="--readout-features-every 10 --action-consistency"
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
PY="${PYTHON:-.venv/bin/python}"
workers=()
[ -n "$WORKERS" ] && workers=(--workers "$WORKERS")
measures=()
RELIANCE_FLAG=""
RELIANCE_NOTE=""
if [ -n "$RELIANCE" ]; then
  measures=(--reliance-every "$RELIANCE")
  RELIANCE_FLAG=" --reliance-every $RELIANCE"
  RELIANCE_NOTE=" Nuisance reliance: the primary camera's background and distractor share of the reliance at every step a multiple of $RELIANCE (docs/faithfulness.md)."
fi
SCRIPT="bash scripts/robustness_reference.sh $TASKS $KINDS $LEVELS $EPISODES"
[ "$SECTION" != Robustness ] && SCRIPT="SECTION=\"$SECTION\" $SCRIPT $OUT"
[ -n "$RELIANCE" ] && SCRIPT="RELIANCE=$RELIANCE $SCRIPT"
"$PY" -m harness.cli robustness --model "$MODEL" --task "$TASKS" --perturb "$KINDS" --levels "$LEVELS" \
    --episodes "$EPISODES" --seed 0 --fast-render --png-every 0 --no-video $PROBES --out "$OUT" "${workers[@]}" \
    "${measures[@]}"
[ "${RUN_ONLY:-}" = 1 ] && exit 0
runs=()
for d in "$OUT"/*/; do [ -f "$d/manifest.json" ] && runs+=("$d"); done
"$PY" -m harness.cli report "${runs[@]}" --out "$OUT/report"
# EVAL.md's "## Robustness" section (other sections stay), or "## $SECTION"
"$PY" -m harness.report.robustness "${runs[@]}" --eval-md "$MODEL/EVAL.md" --section "$SECTION" --command "$SCRIPT" \
    --note "Made by \`$SCRIPT\`: \`octo-harness robustness --model $MODEL --task $TASKS --perturb $KINDS --levels $LEVELS --episodes $EPISODES --seed 0 --fast-render --png-every 0 --no-video $PROBES$RELIANCE_FLAG\` (held-out seeds 0..$((EPISODES - 1)), each task at its own step limit, masks on; kinds and levels: docs/perturbations.md). Target lift and nuisance mass: primary camera, last layer, mean over each episode's steps.$RELIANCE_NOTE $NOTE"
# with reliance: EVAL.md's "## Reliance" section from the nominal run (attention share beside reliance share)
if [ -n "$RELIANCE" ] && [ -f "$OUT/nominal/manifest.json" ]; then
  "$PY" -m harness.probes.reliance.report "$OUT/nominal" --eval-md "$MODEL/EVAL.md" --command "$SCRIPT" --note \
      "Made by \`$SCRIPT\` from its nominal run ($OUT/nominal: held-out seeds 0..$((EPISODES - 1)), --reliance-every $RELIANCE, --reliance-fill impute). $NOTE"
fi
# the figures docs/perturbations.md shows (only for the default grid folder, whose numbers the docs quote)
if [ "$OUT" = results/robustness-reference ]; then
    for png in "$OUT"/report/plots/robustness_*.png; do
        [ -f "$png" ] && cp "$png" "docs/robustness_reference_$(basename "$png" .png | sed 's/^robustness_//').png"
    done
fi

#!/usr/bin/env bash
# Golden runs for refactors that must not change behaviour (issue 42): a Lift run of the committed reference policy
# (PNG overlays, MP4, arrays, recorded inputs), a compare of that run against a second run of the same protocol, an
# HTML report, and a perturbed run (every perturbation kind at level 2, two tasks, one short episode each, so that
# the kinds' seeded draws are held too), and where LIBERO's environment is set up (bash scripts/setup_libero.sh), a
# short LIBERO run of the committed LIBERO-Object reference policy (its server, rot180 frames, masks, platform side;
# issue 72: the suites as registry rows). Writes them under OUT (default results/golden) and prints one line per
# file: its SHA-256 and path, with fields that hold wall-clock times or host paths blanked first
# (scripts/golden_digest.py), so that
#   bash scripts/golden_runs.sh /tmp/before > before.txt   # on the old commit
#   bash scripts/golden_runs.sh /tmp/after > after.txt     # on the new one
#   diff before.txt after.txt                              # empty: the same files, byte for byte
# Same machine only (numerics differ across CPUs). About 80 s on 2 cores, and about 40 s more for the LIBERO run. The
# models are read from copies at fixed paths (GOLDEN_MODEL, GOLDEN_LIBERO_MODEL), since their paths are recorded and drawn.
set -euo pipefail
OUT="${1:-results/golden}"
cd "$(dirname "$0")/.."
PY=.venv/bin/python
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
rm -rf "$OUT"
mkdir -p "$OUT"
# the model's path is recorded (episode.json, manifest.json) and drawn on the overlays: read it from one fixed place,
# so that every checkout (worktree) digests the same
MODEL="${GOLDEN_MODEL:-/tmp/octo-harness-golden-model}"
if ! diff -rq models/octo-reference-robosuite "$MODEL" >/dev/null 2>&1; then
  rm -rf "$MODEL.tmp.$$" && cp -r models/octo-reference-robosuite "$MODEL.tmp.$$" && rm -rf "$MODEL" && mv "$MODEL.tmp.$$" "$MODEL"
fi
run() { "$PY" -m harness.cli run --model "$MODEL" --task Lift --episodes 2 --max-steps 12 \
        --seed 0 --png-every 4 --record-inputs --fast-render --out "$OUT" "$@" >/dev/null 2>&1; }
run --run-name a
run --run-name b
"$PY" -m harness.cli compare "$OUT/a" "$OUT/b" --out "$OUT/compare" >/dev/null 2>&1 || true
"$PY" -m harness.cli report "$OUT/a" --out "$OUT/report" >/dev/null 2>&1
"$PY" -m harness.cli run --model "$MODEL" --task Lift,PickPlaceCan --episodes 1 --max-steps 6 --seed 0 --png-every 0 \
  --record-inputs --fast-render --out "$OUT" --run-name perturbed \
  --perturb camera:2,lighting:2,texture:2,distractors:2,init-state:2,noise:2,language:2 >/dev/null 2>&1
LIBERO_MODEL="${GOLDEN_LIBERO_MODEL:-/tmp/octo-harness-golden-libero-model}"
if [ -x "${OCTO_HARNESS_LIBERO_VENV:-.venv-libero}/bin/python" ]; then
  if ! diff -rq models/octo-reference-libero-object "$LIBERO_MODEL" >/dev/null 2>&1; then
    rm -rf "$LIBERO_MODEL.tmp.$$" && cp -r models/octo-reference-libero-object "$LIBERO_MODEL.tmp.$$" \
      && rm -rf "$LIBERO_MODEL" && mv "$LIBERO_MODEL.tmp.$$" "$LIBERO_MODEL"
  fi
  "$PY" -m harness.cli run --model "$LIBERO_MODEL" --task libero_object/0 --episodes 2 --max-steps 6 --seed 0 \
    --png-every 3 --record-inputs --fast-render --out "$OUT" --run-name libero >/dev/null 2>&1
fi
"$PY" scripts/golden_digest.py "$OUT"

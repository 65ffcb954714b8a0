#!/usr/bin/env bash
# Gate a candidate checkpoint in CI with `octo-harness regress`.
#
#   bash examples/ci/regress-gate.sh CANDIDATE_MODEL [regress options, e.g. --workers 4]
#
# 1. Makes the baseline once: when $BASELINE is missing, it runs $BASELINE_MODEL and keeps a small copy there
#    (scripts/make_baseline.py). Commit that folder, or cache it between CI runs.
# 2. Runs the candidate on the baseline's tasks and seeds until a sequential test decides (`octo-harness regress`).
# 3. Maps regress's exit code to pass or fail, with one line saying which.
#
# Settings (environment variables, with their defaults):
#   BASELINE=results/baselines/ci                  the baseline folder
#   BASELINE_MODEL=models/octo-reference-robosuite the model the baseline is made from (only when it is missing)
#   TASKS=Lift EPISODES=8 MAX_STEPS=80             the baseline's protocol (only when it is made)
#   BASELINE_ARGS=--fast-render                    more `run` options for the baseline
#   FAIL_ON=suspect                                regress's --fail-on; `changed` also fails a change of numerics
#   OUT=results/runs/ci                            where the candidate's run goes
#   OCTO_HARNESS, PYTHON                           the commands (default: this repository's .venv)
#
# Exit codes: 0 pass; 1 fail (the candidate is worse, errored or did not finish);
#             2 no verdict (invalid input such as a damaged checkpoint, an internal error, or an interruption).
set -uo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
BASELINE="${BASELINE:-results/baselines/ci}"
BASELINE_MODEL="${BASELINE_MODEL:-models/octo-reference-robosuite}"
TASKS="${TASKS:-Lift}"
EPISODES="${EPISODES:-8}"
MAX_STEPS="${MAX_STEPS:-80}"
BASELINE_ARGS="${BASELINE_ARGS:---fast-render}"
FAIL_ON="${FAIL_ON:-suspect}"
OUT="${OUT:-results/runs/ci}"
OCTO_HARNESS="${OCTO_HARNESS:-$ROOT/.venv/bin/octo-harness}"
PYTHON="${PYTHON:-$ROOT/.venv/bin/python}"
export HF_HUB_OFFLINE="${HF_HUB_OFFLINE:-1}" MUJOCO_GL="${MUJOCO_GL:-egl}"

if [ $# -lt 1 ]; then
    echo "usage: bash examples/ci/regress-gate.sh CANDIDATE_MODEL [regress options]" >&2
    exit 2
fi
CANDIDATE="$1"
shift

# 1. The baseline, made once. Its policy inputs are recorded, so regress can also replay the candidate on them.
if [ ! -f "$BASELINE/manifest.json" ]; then
    echo "gate: no baseline at $BASELINE; making it once from $BASELINE_MODEL"
    runs="$(mktemp -d)"
    trap 'rm -rf "$runs"' EXIT
    # shellcheck disable=SC2086  # BASELINE_ARGS holds several options
    if ! "$OCTO_HARNESS" run --model "$BASELINE_MODEL" --task "$TASKS" --episodes "$EPISODES" \
            --max-steps "$MAX_STEPS" --png-every 0 --no-video --record-inputs $BASELINE_ARGS \
            --out "$runs" --run-name baseline \
        || ! "$PYTHON" "$ROOT/scripts/make_baseline.py" "$runs/baseline" "$BASELINE"; then
        echo "gate: ERROR: the baseline could not be made (see above)" >&2
        exit 2
    fi
    echo "gate: baseline made at $BASELINE; commit it (or cache it) so later runs gate against the same one"
fi

# 2. The candidate on the baseline's seeds, until the sequential test decides.
"$OCTO_HARNESS" regress --baseline "$BASELINE" --model "$CANDIDATE" --fail-on "$FAIL_ON" --out "$OUT" "$@"
code=$?

# 3. regress's exit codes (docs/regression.md#exit-codes-of-compare-regress-and-replay) as pass or fail.
case "$code" in
    0) echo "gate: PASS: $CANDIDATE holds against $BASELINE"; exit 0 ;;
    1) echo "gate: FAIL: $CANDIDATE regressed against $BASELINE (REGRESSED, SUSPECT, or what --fail-on $FAIL_ON adds)" ;;
    3) echo "gate: FAIL: $CANDIDATE errored on more than half of a task's episodes (ERRORED)" ;;
    4) echo "gate: FAIL: the candidate's run lacks episodes the baseline has (INCOMPLETE)" ;;
    2) echo "gate: ERROR: invalid input, no verdict (a damaged checkpoint or baseline; regress named it above)" >&2; exit 2 ;;
    5) echo "gate: ERROR: internal error of octo-harness, no verdict (a bug: please report it)" >&2; exit 2 ;;
    *) echo "gate: ERROR: regress ended with exit code $code (interrupted?), no verdict" >&2; exit 2 ;;
esac
exit 1

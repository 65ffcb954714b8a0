#!/usr/bin/env bash
# Gate a candidate checkpoint in CI with `octo-harness regress`.
#
#   bash examples/ci/regress-gate.sh CANDIDATE_MODEL [regress options, e.g. --workers 4]
#   OCTO_GATE_BASE_REV=origin/main bash examples/ci/regress-gate.sh models/my-policy   # a pull request's case
#
# 1. Makes the baseline once: when $OCTO_GATE_BASELINE has no manifest.json, it runs $OCTO_GATE_BASELINE_MODEL and
#    keeps a small copy there (scripts/make_baseline.py). With $OCTO_GATE_BASE_REV set, that model is read as it is
#    at that git revision (git archive), not from the working tree: a candidate that replaces the checkpoint in place,
#    at the same path, is then gated against the base's version of it, never against itself.
#    Commit the baseline folder, or cache it keyed on the base's checkpoint (`git rev-parse REV:PATH`, a tree hash),
#    as github-actions.yml beside this script does.
# 2. Runs the candidate on the baseline's tasks and seeds until a sequential test decides (`octo-harness regress`).
# 3. Maps regress's exit code to pass or fail, with one line saying which.
#
# Settings (environment variables, all prefixed OCTO_GATE_ so that the caller's own variables never reach the gate;
# with their defaults). Paths are relative to the current folder:
#   OCTO_GATE_BASELINE=results/baselines/ci                   the baseline folder; with OCTO_GATE_BASE_REV set,
#                                                             results/baselines/ci-<first 12 digits of the base's tree>
#   OCTO_GATE_BASELINE_MODEL=models/octo-reference-robosuite  the checkpoint the baseline is made from (only when
#                                                             the baseline is missing)
#   OCTO_GATE_BASE_REV=                                       a git revision (the pull request's base commit) to read
#                                                             OCTO_GATE_BASELINE_MODEL from; empty: the working tree
#   OCTO_GATE_TASKS=Lift OCTO_GATE_EPISODES=8 OCTO_GATE_MAX_STEPS=80   the baseline's protocol (when it is made)
#   OCTO_GATE_BASELINE_ARGS=--fast-render                     more `run` options for the baseline
#   OCTO_GATE_FAIL_ON=suspect                                 regress's --fail-on; `changed` also fails a change of
#                                                             numerics
#   OCTO_GATE_OUT=results/runs/ci                             where the candidate's run goes
#   OCTO_GATE_HARNESS, OCTO_GATE_PYTHON                       the commands (default: this repository's .venv)
#
# A checkpoint kept in Git LFS is read at OCTO_GATE_BASE_REV as its pointer files (git archive does not smudge them):
# check out the base with `git worktree add` and `git lfs pull` there, point OCTO_GATE_BASELINE_MODEL at it and leave
# OCTO_GATE_BASE_REV unset.
#
# Exit codes: 0 pass; 1 fail (the candidate is worse, errored or did not finish; regress wrote its regress.json);
#             2 no verdict (invalid input such as a damaged checkpoint or an unknown base revision, an internal error
#               or a crash that wrote no verdict, or an interruption).
set -uo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
GATE_BASELINE_MODEL="${OCTO_GATE_BASELINE_MODEL:-models/octo-reference-robosuite}"
GATE_BASE_REV="${OCTO_GATE_BASE_REV:-}"
GATE_TASKS="${OCTO_GATE_TASKS:-Lift}"
GATE_EPISODES="${OCTO_GATE_EPISODES:-8}"
GATE_MAX_STEPS="${OCTO_GATE_MAX_STEPS:-80}"
GATE_BASELINE_ARGS="${OCTO_GATE_BASELINE_ARGS:---fast-render}"
GATE_FAIL_ON="${OCTO_GATE_FAIL_ON:-suspect}"
GATE_OUT="${OCTO_GATE_OUT:-results/runs/ci}"
GATE_HARNESS="${OCTO_GATE_HARNESS:-$ROOT/.venv/bin/octo-harness}"
GATE_PYTHON="${OCTO_GATE_PYTHON:-$ROOT/.venv/bin/python}"
export HF_HUB_OFFLINE="${HF_HUB_OFFLINE:-1}" MUJOCO_GL="${MUJOCO_GL:-egl}"

if [ $# -lt 1 ]; then
    echo "usage: bash examples/ci/regress-gate.sh CANDIDATE_MODEL [regress options]" >&2
    exit 2
fi
CANDIDATE="$1"
shift

scratch="$(mktemp -d)"
trap 'rm -rf "$scratch"' EXIT

# 0. The base checkpoint: which commit and git tree it is, checked before anything runs.
if [ -n "$GATE_BASE_REV" ]; then
    top="$(git rev-parse --show-toplevel 2>/dev/null)" || {
        echo "gate: ERROR: OCTO_GATE_BASE_REV=$GATE_BASE_REV, but $(pwd) is not in a git repository" >&2; exit 2; }
    rel="$(realpath -m --relative-to="$top" "$GATE_BASELINE_MODEL")"
    commit="$(git -C "$top" rev-parse --verify --quiet "$GATE_BASE_REV^{commit}")" || {
        echo "gate: ERROR: OCTO_GATE_BASE_REV=$GATE_BASE_REV is not a commit of $top (fetch it, or clone with more history)" >&2
        exit 2; }
    tree="$(git -C "$top" rev-parse --verify --quiet "$commit:$rel")" \
        && [ "$(git -C "$top" cat-file -t "$tree")" = tree ] || {
        echo "gate: ERROR: $rel is not a folder at $GATE_BASE_REV ($commit): no base checkpoint to make the baseline from" >&2
        exit 2; }
    base_desc="$rel as at $GATE_BASE_REV (commit $commit, tree $tree)"
    # One folder per base checkpoint: a baseline made from another base is never reused by mistake.
    GATE_BASELINE="${OCTO_GATE_BASELINE:-results/baselines/ci-${tree:0:12}}"
else
    base_desc="$GATE_BASELINE_MODEL in the working tree"
    GATE_BASELINE="${OCTO_GATE_BASELINE:-results/baselines/ci}"
fi

# 1. The baseline, made once. Its policy inputs are recorded, so regress can also replay the candidate on them.
if [ ! -f "$GATE_BASELINE/manifest.json" ]; then
    echo "gate: no baseline at $GATE_BASELINE; making it once from $base_desc"
    if [ -n "$GATE_BASE_REV" ]; then
        # The base's checkpoint, read from git at that commit into a scratch folder (git archive: no checkout needed).
        mkdir -p "$scratch/base-${commit:0:12}"
        if ! git -C "$top" archive --format=tar "$commit" -- "$rel" | tar -x -C "$scratch/base-${commit:0:12}"; then
            echo "gate: ERROR: could not read $rel at $commit" >&2
            exit 2
        fi
        source_model="$scratch/base-${commit:0:12}/$rel"
    else
        source_model="$GATE_BASELINE_MODEL"
        if [ -e "$CANDIDATE" ] && [ "$(realpath "$CANDIDATE")" = "$(realpath -m "$GATE_BASELINE_MODEL")" ]; then
            echo "gate: WARNING: the candidate is the baseline model's own folder and OCTO_GATE_BASE_REV is unset: this" \
                 "gates the candidate against itself; set OCTO_GATE_BASE_REV to the base commit" >&2
        fi
    fi
    # shellcheck disable=SC2086  # GATE_BASELINE_ARGS holds several options
    if ! "$GATE_HARNESS" run --model "$source_model" --task "$GATE_TASKS" --episodes "$GATE_EPISODES" \
            --max-steps "$GATE_MAX_STEPS" --png-every 0 --no-video --record-inputs $GATE_BASELINE_ARGS \
            --out "$scratch/runs" --run-name baseline \
        || ! "$GATE_PYTHON" "$ROOT/scripts/make_baseline.py" "$scratch/runs/baseline" "$GATE_BASELINE"; then
        echo "gate: ERROR: the baseline could not be made (see above)" >&2
        exit 2
    fi
    echo "gate: baseline made at $GATE_BASELINE; commit it (or cache it) so later runs gate against the same one"
else
    echo "gate: baseline at $GATE_BASELINE, made earlier (remove it to make it again from $base_desc)"
fi

# 2. The candidate on the baseline's seeds, until the sequential test decides. Its report's path is the last line
#    `regress: .../regress.json`: a verdict is read only from a run that wrote one.
"$GATE_HARNESS" regress --baseline "$GATE_BASELINE" --model "$CANDIDATE" --fail-on "$GATE_FAIL_ON" --out "$GATE_OUT" "$@" \
    | tee "$scratch/regress.out"
code=${PIPESTATUS[0]}
report="$(sed -n 's/^regress: \(.*regress\.json\)$/\1/p' "$scratch/regress.out" | tail -n 1)"
case "$code" in
    0|1|3|4) if [ -z "$report" ] || [ ! -f "$report" ]; then
                 # A crash before the verdict (an uncaught Python error also exits 1) is no verdict, never a FAIL.
                 echo "gate: ERROR: regress ended with exit code $code but wrote no regress.json (a crash?), no verdict" >&2
                 exit 2
             fi ;;
esac

# 3. regress's exit codes (docs/regression.md#exit-codes-of-compare-regress-and-replay) as pass or fail.
case "$code" in
    0) echo "gate: PASS: $CANDIDATE holds against $GATE_BASELINE ($report)"; exit 0 ;;
    1) echo "gate: FAIL: $CANDIDATE regressed against $GATE_BASELINE (REGRESSED, SUSPECT, or what --fail-on $GATE_FAIL_ON adds; $report)" ;;
    3) echo "gate: FAIL: $CANDIDATE errored on more than half of a task's episodes (ERRORED; $report)" ;;
    4) echo "gate: FAIL: the candidate's run lacks episodes the baseline has (INCOMPLETE; $report)" ;;
    2) echo "gate: ERROR: invalid input, no verdict (a damaged checkpoint or baseline; regress named it above)" >&2; exit 2 ;;
    5) echo "gate: ERROR: internal error of octo-harness, no verdict (a bug: please report it)" >&2; exit 2 ;;
    *) echo "gate: ERROR: regress ended with exit code $code (interrupted?), no verdict" >&2; exit 2 ;;
esac
exit 1

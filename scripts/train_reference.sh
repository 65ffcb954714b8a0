#!/usr/bin/env bash
# Rebuild the reference policy in models/octo-reference-robosuite from scratch with fixed seeds:
# scripted-expert demonstrations (data/reference_demos/, not committed), then training on the CPU.
# Extra arguments go to `python -m harness.reference.pipeline` (--episodes, --steps, --out, --data, --workers).
source "$(dirname "$0")/_bootstrap.sh"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
exec .venv/bin/python -m harness.reference.pipeline "$@"

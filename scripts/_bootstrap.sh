# Sourced by scripts/demo.sh and scripts/test.sh: installs system libraries (as root) and the .venv.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

APT_PACKAGES="libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libgl1 libglib2.0-0 libosmesa6"
python3 -c "import ensurepip, venv" 2>/dev/null || APT_PACKAGES="$APT_PACKAGES python3-venv"
missing=""
for p in $APT_PACKAGES; do
    dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
done
if [ -n "$missing" ]; then
    if [ "$(id -u)" = "0" ]; then
        echo "[setup] installing system libraries:$missing"
        DEBIAN_FRONTEND=noninteractive apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $missing >/dev/null
    else
        echo "[setup] missing system libraries; run: sudo apt-get install -y$missing" >&2
        exit 1
    fi
fi

STAMP=".venv/.installed-$(sha1sum pyproject.toml | cut -c1-12)"
if [ ! -f "$STAMP" ]; then
    echo "[setup] creating .venv and installing octo-harness (first run takes a few minutes)"
    venv_start=$(date +%s)
    python3 -m venv .venv
    .venv/bin/pip install -q --upgrade pip
    # --no-compile: Python compiles each module's bytecode when it is first imported (and keeps it), instead of pip
    # compiling every file of every package up front (half of the LIBERO stack's install time, measured)
    .venv/bin/pip install -q --no-compile -e ".[test,ray,viewer,train,served]"
    rm -f .venv/.installed-*
    touch "$STAMP"
    echo "[setup] .venv ready ($(( $(date +%s) - venv_start )) s)"
fi

export MUJOCO_GL="${MUJOCO_GL:-egl}"
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-$MUJOCO_GL}"
# Both venvs are installed with --no-compile: each module's bytecode is written on first import and read after. A
# set PYTHONDONTWRITEBYTECODE (some container images set it) stops that write, so every process the demo or the test
# suite starts (CLI commands, spawned env workers, Ray workers, LIBERO servers) would compile the same ~1,900 modules
# from source again: ~4 s of CPU per process on a 2-core EPYC (imports 6.3-7.2 s without bytecode, 2.3-2.5 s with).
unset PYTHONDONTWRITEBYTECODE

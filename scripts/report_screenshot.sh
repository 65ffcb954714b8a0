#!/usr/bin/env bash
# Rebuild the README's report screenshot from run folders:  bash scripts/report_screenshot.sh RUN_DIR [RUN_DIR ...]
# Builds `octo-harness report` into a temporary folder, opens it in headless Chromium and writes
# docs/report_screenshot.png (960 px wide, the top of the page: cross-task comparison).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
[ "$#" -ge 1 ] || { echo "usage: bash scripts/report_screenshot.sh RUN_DIR [RUN_DIR ...]" >&2; exit 2; }
command -v chromium >/dev/null || { echo "needs Debian's chromium: apt-get install -y --no-install-recommends chromium" >&2; exit 1; }
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT
"$ROOT/.venv/bin/octo-harness" report "$@" --out "$TMP/report"
chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run --disable-background-networking \
    --disable-component-update --disable-sync --user-data-dir="$TMP/profile" --hide-scrollbars \
    --window-size=1280,1500 --screenshot="$TMP/shot.png" "file://$TMP/report/report.html" 2>/dev/null
"$ROOT/.venv/bin/python" - "$TMP/shot.png" "$ROOT/docs/report_screenshot.png" <<'PY'
import sys
from PIL import Image
image = Image.open(sys.argv[1]).convert("RGB")
image = image.resize((960, round(image.height * 960 / image.width)), Image.LANCZOS)
image.quantize(colors=192, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(sys.argv[2], optimize=True)
print(f"wrote {sys.argv[2]}")
PY

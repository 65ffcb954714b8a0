#!/usr/bin/env bash
# Rebuild the report screenshots from run folders:  bash scripts/report_screenshot.sh RUN_DIR [RUN_DIR ...]
# Builds `octo-harness report` into a temporary folder, opens it in headless Chromium at two window widths and writes
# the top of the page (cross-task comparison): docs/report_screenshot.png (1280 px wide, shown at 960) and
# docs/report_screenshot_800.png (800 px wide, a narrow window).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
[ "$#" -ge 1 ] || { echo "usage: bash scripts/report_screenshot.sh RUN_DIR [RUN_DIR ...]" >&2; exit 2; }
command -v chromium >/dev/null || { echo "needs Debian's chromium: apt-get install -y --no-install-recommends chromium" >&2; exit 1; }
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT
"$ROOT/.venv/bin/octo-harness" report "$@" --out "$TMP/report"
shot() {  # shot WIDTH HEIGHT PNG
  chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run --disable-background-networking \
      --disable-component-update --disable-sync --user-data-dir="$TMP/profile" --hide-scrollbars \
      --window-size="$1,$2" --screenshot="$3" "file://$TMP/report/report.html" 2>/dev/null
}
shot 1280 1700 "$TMP/wide.png"
shot 800 1900 "$TMP/narrow.png"
"$ROOT/.venv/bin/python" - "$TMP" "$ROOT/docs" <<'PY'
import sys
from pathlib import Path
from PIL import Image
tmp, docs = Path(sys.argv[1]), Path(sys.argv[2])
for name, out, width in (("wide", "report_screenshot.png", 960), ("narrow", "report_screenshot_800.png", 800)):
    image = Image.open(tmp / f"{name}.png").convert("RGB")
    image = image.resize((width, round(image.height * width / image.width)), Image.LANCZOS)
    image.quantize(colors=192, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(docs / out, optimize=True)
    print(f"wrote {docs / out}")
PY

#!/usr/bin/env bash
# Rebuild docs/viewer_screenshot.png: the Rerun web viewer on a real episode of the reference policy.
#   bash scripts/viewer_screenshot.sh [STEP]
# Runs models/octo-reference-robosuite on Lift (seed 0, --rerun save) into a temporary folder, serves the episode with
# `octo-harness view --serve`, screenshots the web viewer in headless Chromium (WebGL on SwiftShader) and writes a
# 1200 px wide PNG. The viewer opens at the episode's last step.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-$ROOT/.venv/bin/python}"
command -v chromium >/dev/null || { echo "needs Debian's chromium: apt-get install -y --no-install-recommends chromium" >&2; exit 1; }
export MUJOCO_GL="${MUJOCO_GL:-egl}" PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}" HF_HUB_OFFLINE=1
TMP="$(mktemp -d)"
SERVER=""
trap '[ -n "$SERVER" ] && kill -INT "$SERVER" 2>/dev/null; rm -rf "$TMP"' EXIT
cd "$ROOT"
"$PY" -m harness.cli run --model models/octo-reference-robosuite --task Lift --episodes 1 --seed 0 --png-every 0 \
    --rerun save --out "$TMP" --run-name lift
"$PY" -m harness.cli view "$TMP/lift" --serve --viewer-port 9878 --web-port 9092 > "$TMP/serve.log" 2>&1 &
SERVER=$!
for _ in $(seq 120); do grep -q "Rerun web viewer: " "$TMP/serve.log" && break; sleep 1; done
URL="$(sed -n 's/.*Rerun web viewer: \([^ ;]*\).*/\1/p' "$TMP/serve.log" | head -1)"
[ -n "$URL" ] || { cat "$TMP/serve.log" >&2; exit 1; }
RENDERED=0
for budget in 30000 90000 180000; do  # the viewer's WebAssembly compiles in real CPU time; later tries hit the code cache
    chromium --headless --no-sandbox --use-angle=swiftshader --enable-unsafe-swiftshader --ignore-gpu-blocklist \
        --no-first-run --disable-background-networking --user-data-dir="$TMP/profile" --window-size=1600,1000 \
        --virtual-time-budget=$budget --screenshot="$TMP/shot.png" "$URL" 2>/dev/null
    if "$PY" -c "import sys, numpy as np; from PIL import Image; a = np.asarray(Image.open(sys.argv[1]).convert('RGB')).astype(int); sys.exit(0 if a.std() > 20 and len(np.unique(a.reshape(-1, 3) // 8, axis=0)) > 200 else 1)" "$TMP/shot.png"; then
        RENDERED=1; break
    fi
done
[ "$RENDERED" = 1 ] || { echo "the web viewer did not render in headless Chromium (the screenshot shows its loading screen)" >&2; exit 1; }
"$PY" - "$TMP/shot.png" "$ROOT/docs/viewer_screenshot.png" <<'PY'
import sys
from PIL import Image
image = Image.open(sys.argv[1]).convert("RGB")
image = image.resize((1200, round(image.height * 1200 / image.width)), Image.LANCZOS)
image.quantize(colors=192, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(sys.argv[2], optimize=True)
print(f"wrote {sys.argv[2]}")
PY

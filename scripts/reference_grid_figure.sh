#!/usr/bin/env bash
# The README's old-versus-new picture of the reference policy's patch grid: the same Lift episode (seed 1, which
# both lift) run by two checkpoints, one overlay panel (layer 1, every head) and one MP4 frame at the same step from
# each, stacked into docs/reference_grid_panels.png and docs/reference_grid_video.png.
#   bash scripts/reference_grid_figure.sh [OLD_MODEL] [NEW_MODEL] [STEP] [LAYER] [SEED]
set -euo pipefail
cd "$(dirname "$0")/.."
OLD="${1:-models/octo-reference-robosuite-64px}"
NEW="${2:-models/octo-reference-robosuite}"
STEP="${3:-12}"
LAYER="${4:-1}"
SEED="${5:-1}"
RUNS="$(mktemp -d)"
trap 'rm -rf "$RUNS"' EXIT
export HF_HUB_OFFLINE=1 MUJOCO_GL="${MUJOCO_GL:-egl}"
for side in old new; do
    model=$OLD; [ "$side" = new ] && model=$NEW
    .venv/bin/octo-harness run --model "$model" --task Lift --episodes 1 --seed "$SEED" --max-steps "$((STEP + 1))" \
        --fast-render --png-every "$STEP" --layers "$LAYER" --video-attention "$LAYER" --out "$RUNS" --run-name "$side"
done
.venv/bin/python - "$RUNS" "$STEP" "$OLD" "$NEW" "$LAYER" <<'PY'
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from PIL import Image, ImageDraw

runs, step, old, new, layer = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4], int(sys.argv[5])


def labelled(image: np.ndarray, text: str) -> np.ndarray:
    canvas = Image.new("RGB", (image.shape[1], image.shape[0] + 20), "white")
    canvas.paste(Image.fromarray(image), (0, 20))
    ImageDraw.Draw(canvas).text((4, 3), text, fill="black")
    return np.asarray(canvas)


def stack(images: list[np.ndarray]) -> np.ndarray:
    width = max(i.shape[1] for i in images)
    return np.concatenate([np.pad(i, ((0, 0), (0, width - i.shape[1]), (0, 0)), constant_values=255) for i in images])


panels, frames = [], []
for side, model in (("old", old), ("new", new)):
    episode = runs / side / "Lift" / "episode_0"
    panels.append(labelled(iio.imread(episode / f"step_{step:04d}_layer_{layer:02d}.png")[..., :3], f"{side}: {model}"))
    video = iio.imread(episode / "rollout.mp4", index=step)
    frames.append(labelled(video, f"{side}: {model}, MP4 frame {step}"))
Image.fromarray(stack(panels)).save("docs/reference_grid_panels.png", optimize=True)
Image.fromarray(stack(frames)).save("docs/reference_grid_video.png", optimize=True)
print("wrote docs/reference_grid_panels.png and docs/reference_grid_video.png")
PY

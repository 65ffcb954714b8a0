"""The Failures section's pictures (harness.report.failures): an episode's frame at chosen steps, as the run recorded
it, and one PNG a task of failed frames beside successful ones.

Where a frame comes from (`source`, `panels`), decoding only the steps shown:
- rollout.mp4: the video's first camera row, camera | attention overlay as the run drew them (its --video-attention,
  by default the last layer's head mean; a policy without attention: the camera alone), read from the top-left of
  the chosen frames (harness.report.frames.read_video_frames; frame n is step n);
- else inputs.npz (--record-inputs): the policy's input frame of that camera at that step, beside the same frame with
  the episode's readout attention at that step drawn over it (attention.npz, last layer, head and readout mean,
  harness.outputs.overlays.heatmap_overlay in the run's colour map); a policy without attention: the frame alone;
- else nothing (a run with --no-video and without --record-inputs).
Every panel is scaled to PANEL pixels high. `compose` lays the rows out: a title, then per row two header lines and
the failed panel beside the successful one (a grey box with a line where there is none).
"""

from __future__ import annotations

import io

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from harness.analysis.runs import read_npz
from harness.outputs.overlays import PAD, heatmap_overlay
from harness.report.frames import VIDEO_DISPLAY, npz_row, read_video_frames

PANEL = 160  # pixel height of a panel (the video's 256 px rows, scaled down)
MARGIN, GAP, TITLE, HEADER, ROW_GAP, LINE = 6, 20, 22, 34, 10, 15  # the figure's layout in pixels
INPUTS = "inputs.npz"
TOKENS = tuple(f"tokens/{n}" for n in ("group", "timestep", "row", "col", "image_groups", "image_keys", "image_grids",
                                        "readout_index"))  # what TokenMap.from_arrays reads


def source(episode) -> str | None:
    """What an episode recorded its frames in: "rollout.mp4", "inputs.npz", or None."""
    if episode.video_path is not None:
        return "rollout.mp4"
    return INPUTS if (episode.directory / INPUTS).is_file() else None


def recorded_steps(episode) -> list[int]:
    """The steps an episode has a frame of (rollout.mp4: every step; inputs.npz: its recorded steps, which a baseline
    may have cut short); [] without frames."""
    kind = source(episode)
    if kind == "rollout.mp4":
        return list(range(max(int(episode.steps or 0), 0)))
    if kind == INPUTS:
        try:
            return sorted(int(s) for s in read_npz(episode.directory / INPUTS, "step", steps=episode.steps or None)["step"])
        except (OSError, KeyError, ValueError):
            return []
    return []


def at_or_before(recorded: list[int], wanted: int) -> int:
    """The recorded step to show for `wanted`: the last one at or before it, else the first one (else `wanted`)."""
    before = [s for s in recorded if s <= wanted]
    return before[-1] if before else (recorded[0] if recorded else wanted)


def _tokens(episode):
    from harness.octo.tokens import TokenMap

    path = episode.attention_path
    try:
        return TokenMap.from_arrays(read_npz(path, *TOKENS, steps=episode.steps or None))
    except (OSError, KeyError, ValueError):
        return None


def _camera(run, episode, tokens) -> tuple[str | None, float]:
    """The video's first camera row (the run's --video-cameras, else the model's first camera) and its width / height."""
    options = episode.read_json().get("options") or {}
    chosen = options.get("video_camera")
    chosen = chosen[0] if isinstance(chosen, list) and chosen else chosen
    model = run.record.manifest.get("model") if isinstance(run.record.manifest, dict) else None
    sizes = (model or {}).get("image_sizes") or {}
    if not isinstance(chosen, str):
        chosen = tokens.image_groups[0][1] if tokens is not None and tokens.image_groups else next(iter(sizes), None)
    size = sizes.get(chosen)
    if isinstance(size, (list, tuple)) and len(size) == 2 and min(size) > 0:
        return chosen, float(size[1]) / float(size[0])
    grid = [(r, c) for _, key, r, c in (tokens.image_groups if tokens is not None else ()) if key == chosen]
    return chosen, (grid[0][1] / grid[0][0] if grid else 1.0)


def _fit(image: np.ndarray, height: int = PANEL) -> np.ndarray:
    """image scaled to `height` pixels high (area average down, nearest neighbour up)."""
    h, w = image.shape[:2]
    width = max(1, int(round(w * height / h)))
    resample = Image.BOX if h > height else Image.NEAREST
    return np.asarray(Image.fromarray(image).resize((width, height), resample))


def _side(*images: np.ndarray) -> np.ndarray:
    """Images of one height left to right, PAD white pixels apart."""
    out = [images[0]]
    for image in images[1:]:
        out += [np.full((images[0].shape[0], PAD, 3), 255, np.uint8), image]
    return np.concatenate(out, axis=1)


def _video_panels(run, episode, steps: list[int], aspect: float) -> dict[int, np.ndarray]:
    width = max(1, int(round(VIDEO_DISPLAY * aspect)))
    if run.record.attention:  # camera | PAD | overlay (harness.outputs.overlays.video_frame's first row)
        width = 2 * width + PAD
    frames = read_video_frames(episode.video_path, steps, VIDEO_DISPLAY, width)
    return {s: _fit(frames[s]) for s in steps if s in frames}


def _input_panels(run, episode, steps: list[int], camera: str | None, tokens) -> dict[int, np.ndarray]:
    inputs, limit = episode.directory / INPUTS, episode.steps or None
    try:
        recorded = [int(s) for s in read_npz(inputs, "step", steps=limit)["step"]]
        attention = None
        if run.record.attention and tokens is not None and camera in [k for _, k, _, _ in tokens.image_groups]:
            attention = [int(s) for s in read_npz(episode.attention_path, "step", steps=limit)["step"]]
    except (OSError, KeyError, ValueError):
        return {}
    cmap = (episode.read_json().get("options") or {}).get("cmap") or "viridis"
    out = {}
    for step in steps:
        if step not in recorded:
            continue
        try:
            frame = npz_row(inputs, f"input/{camera}", recorded.index(step), limit)
            row = (npz_row(episode.attention_path, "readout_attention", attention.index(step), limit)
                   if attention is not None and step in attention else None)
        except (OSError, ValueError):
            continue
        if frame is None or frame.ndim != 3 or frame.shape[2] != 3:
            continue
        frame = _fit(np.asarray(frame, np.uint8))
        if row is None:
            out[step] = frame
            continue
        from harness.measures.attention import camera_maps

        shown = camera_maps(np.asarray(row, np.float32)[-1].mean(axis=(0, 1)), tokens, camera)  # last layer
        try:
            overlay = heatmap_overlay(frame, shown, cmap=cmap)
        except ValueError:  # a colour map this matplotlib lacks
            overlay = heatmap_overlay(frame, shown)
        out[step] = _side(frame, overlay)
    return out


def panels(run, episode, steps: list[int]) -> dict[int, tuple[np.ndarray, str]]:
    """{step: (panel (PANEL, w, 3) uint8, where it came from)} of an episode's frames at `steps` (those it has)."""
    tokens = _tokens(episode) if run.record.attention else None
    camera, aspect = _camera(run, episode, tokens)
    if episode.video_path is not None:
        found = _video_panels(run, episode, steps, aspect)
        if found:
            return {s: (image, "rollout.mp4") for s, image in found.items()}
    if (episode.directory / INPUTS).is_file() and camera is not None:
        return {s: (image, INPUTS) for s, image in _input_panels(run, episode, steps, camera, tokens).items()}
    return {}


def _font(size: int) -> ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType: its fixed bitmap font
        return ImageFont.load_default()


def compose(title: str, rows: list[tuple]) -> bytes:
    """PNG: the title, then per row (left panel or None, its two header lines, right panel or None, its lines) the
    failed panel beside the successful one; a missing panel is a grey box as wide as the other (or PANEL)."""
    font = _font(12)

    def text(lines) -> int:
        return max(int(font.getlength(line)) for line in lines)

    widths = [(left[0].shape[1] if left else None, right[0].shape[1] if right else None) for left, _, right, _ in rows]
    widths = [(lw or rw or PANEL, rw or lw or PANEL) for lw, rw in widths]
    left_w = max(max(lw, text(r[1])) for (lw, _), r in zip(widths, rows))
    right_w = max(max(rw, text(r[3])) for (_, rw), r in zip(widths, rows))
    width = max(2 * MARGIN + left_w + GAP + right_w, 2 * MARGIN + int(font.getlength(title)))
    height = TITLE + len(rows) * (HEADER + PANEL + ROW_GAP)
    canvas = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(canvas)
    draw.text((MARGIN, 4), title, fill=(0, 0, 0), font=font)
    for i, ((left, left_lines, right, right_lines), (lw, rw)) in enumerate(zip(rows, widths)):
        top = TITLE + i * (HEADER + PANEL + ROW_GAP)
        for x, panel, lines, w, colour in ((MARGIN, left, left_lines, lw, (170, 30, 30)),
                                           (MARGIN + left_w + GAP, right, right_lines, rw, (20, 110, 40))):
            for j, line in enumerate(lines[:2]):
                draw.text((x, top + 2 + j * LINE), line, fill=colour if j == 0 else (0, 0, 0), font=font)
            if panel is not None:
                canvas.paste(Image.fromarray(panel[0]), (x, top + HEADER))
            else:
                draw.rectangle([x, top + HEADER, x + w - 1, top + HEADER + PANEL - 1], fill=(225, 225, 225))
                draw.text((x + 6, top + HEADER + PANEL // 2 - 7), "no frame", fill=(90, 90, 90), font=font)
    out = io.BytesIO()
    canvas.save(out, format="PNG", optimize=False, compress_level=6)
    return out.getvalue()


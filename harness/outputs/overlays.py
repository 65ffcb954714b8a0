"""Overlays: attention maps drawn over camera frames, as (H, W, 3) uint8 numpy images.

Fast enough to run every control step: colours come from a 256-entry lookup table built once per
colormap from matplotlib's colormaps (no figures), blending is integer numpy, text and boxes are
drawn with Pillow's ImageDraw. Maps are drawn patch-constant by default (interpolation "nearest",
`harness.measures.attention.upsample_map`: a patch of the model's grid lights exactly the block of pixels it was
cut from, in the frame's own orientation); interpolation "bilinear" interpolates the map's values between patch
centres before colouring (the smooth look of the original attention-visualisation scripts; it shows no detail the
patch grid does not have).

- `heatmap_overlay`: one map over one frame.
- `layer_panel`: one step and layer, every head and the fused head per camera, captions, colour bars.
- `attribution_panel`: one step, every attribution method per camera (each map over its own range).
- `video_frame`: one row per camera, camera frame | attention overlay | captions, over a strip of per-layer overlays.
"""

from __future__ import annotations

import textwrap
from functools import lru_cache
from typing import Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from harness.measures.attention import fuse_heads

INTERPOLATIONS = ("nearest", "bilinear")  # how a patch-grid map is enlarged to its frame (--overlay-interpolation)
BACKGROUND = 255
TEXT = (0, 0, 0)
BOX = (0, 255, 0)
PAD = 4
COLORBAR_WIDTH = 12


@lru_cache(maxsize=8)
def colormap_lut(name: str) -> np.ndarray:
    """(256, 3) uint8 lookup table of a matplotlib colormap (computed once per name)."""
    import matplotlib

    try:
        cmap = matplotlib.colormaps[name]
    except KeyError:
        raise ValueError(f"unknown colormap {name!r}; use a matplotlib colormap name such as 'jet' or 'inferno'") from None
    lut = np.round(cmap(np.linspace(0.0, 1.0, 256))[:, :3] * 255).astype(np.uint8)
    lut.setflags(write=False)
    return lut


@lru_cache(maxsize=8)
def _font(size: int) -> ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType: fixed-size bitmap font
        return ImageFont.load_default()


def colorize(values: np.ndarray, vmin: float, vmax: float, cmap: str = "viridis") -> np.ndarray:
    """values (...) -> (..., 3) uint8: (v - vmin) / (vmax - vmin) clipped to [0, 1] through the colormap.

    A degenerate range (vmax <= vmin) maps everything to the coldest colour.
    """
    values = np.asarray(values, dtype=np.float32)
    span = float(vmax) - float(vmin)
    if span > 0:
        index = np.clip(np.rint((values - vmin) * (255.0 / span)), 0, 255).astype(np.uint8)
    else:
        index = np.zeros(values.shape, np.uint8)
    return colormap_lut(cmap)[index]


def resize_nearest(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """image (h, w, ...) -> (height, width, ...) by nearest neighbour (integer scales repeat pixels exactly)."""
    h, w = image.shape[:2]
    if (h, w) == (height, width):
        return image
    ry = (np.arange(height) * h) // height
    cx = (np.arange(width) * w) // width
    return image[ry[:, None], cx[None, :]]


def _check_frame(frame: np.ndarray) -> np.ndarray:
    frame = np.asarray(frame)
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise ValueError(f"frames must be (height, width, 3) uint8; got {frame.shape} {frame.dtype}")
    return frame


def _upsample_colours(colours: np.ndarray, height: int, width: int) -> np.ndarray:
    """colours (rows, cols, C) -> (height, width, C) patch-constant (same pixels as attention.upsample_map)."""
    rows, cols = colours.shape[:2]
    if height % rows == 0 and width % cols == 0:  # fast path: whole blocks
        return np.repeat(np.repeat(colours, height // rows, axis=0), width // cols, axis=1)
    return resize_nearest(colours, height, width)


def check_interpolation(interpolation: str) -> str:
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"overlay interpolation must be one of {', '.join(INTERPOLATIONS)}; got {interpolation!r}")
    return interpolation


def _bilinear_weights(size: int, cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lower cell, upper cell, weight of the upper) for each of `size` pixels over `cells` cells, cell centres at
    (i + 0.5) * size / cells (half-pixel centres, as PIL and OpenCV); clamped at the borders."""
    position = (np.arange(size) + 0.5) * cells / size - 0.5
    low = np.clip(np.floor(position), 0, cells - 1).astype(np.intp)
    high = np.minimum(low + 1, cells - 1)
    weight = np.clip(position - low, 0.0, 1.0).astype(np.float32)
    return low, high, weight


def upsample_bilinear(maps: np.ndarray, height: int, width: int) -> np.ndarray:
    """maps (..., rows, cols) -> (..., height, width) float32, bilinear between patch centres (edges held)."""
    maps = np.asarray(maps, dtype=np.float32)
    rows, cols = maps.shape[-2:]
    y0, y1, wy = _bilinear_weights(height, rows)
    x0, x1, wx = _bilinear_weights(width, cols)
    columns = maps[..., x0] * (1 - wx) + maps[..., x1] * wx  # (..., rows, width)
    return columns[..., y0, :] * (1 - wy)[:, None] + columns[..., y1, :] * wy[:, None]


def heatmap_overlays(
    frame: np.ndarray,
    maps: np.ndarray,
    vmin: float | np.ndarray | None = None,
    vmax: float | np.ndarray | None = None,
    alpha: float = 0.5,
    cmap: str = "viridis",
    interpolation: str = "nearest",
) -> np.ndarray:
    """frame (H, W, 3) uint8, maps (n, rows, cols) -> (n, H, W, 3) uint8 overlays of each map on the frame.

    vmin / vmax: scalars or (n,) per map; None = each map's own min / max. Each map is coloured per
    patch and upsampled patch-constant to the frame ("nearest"), or interpolated bilinearly to the frame
    and coloured per pixel ("bilinear"), then blended as (1 - alpha) * frame + alpha * colour in integer
    arithmetic (the frame part is computed once for all maps).
    """
    frame = _check_frame(frame)
    check_interpolation(interpolation)
    maps = np.asarray(maps, dtype=np.float32)
    n = maps.shape[0]
    lo = maps.min(axis=(1, 2)) if vmin is None else np.broadcast_to(np.asarray(vmin, np.float32), (n,))
    hi = maps.max(axis=(1, 2)) if vmax is None else np.broadcast_to(np.asarray(vmax, np.float32), (n,))
    span = (hi - lo)[:, None, None]
    scaled = np.divide((maps - lo[:, None, None]) * 255.0, span, out=np.zeros_like(maps), where=span > 0)
    index = np.clip(np.rint(scaled), 0, 255).astype(np.uint8)  # (n, rows, cols)
    a = int(round(float(np.clip(alpha, 0.0, 1.0)) * 256))
    lut = colormap_lut(cmap).astype(np.uint16) * a  # (256, 3) colour weighted by alpha
    base = frame.astype(np.uint16) * (256 - a) + 128  # (H, W, 3); max total 255 * 256 + 128 fits uint16
    height, width = frame.shape[:2]
    out = np.empty((n, height, width, 3), np.uint8)
    if interpolation == "bilinear":  # values between patch centres, then coloured per pixel (range as above)
        smooth = upsample_bilinear(maps, height, width)
        scaled = np.divide((smooth - lo[:, None, None]) * 255.0, span, out=np.zeros_like(smooth), where=span > 0)
        index = np.clip(np.rint(scaled), 0, 255).astype(np.uint8)  # (n, H, W)
        for i in range(n):
            out[i] = (base + lut[index[i]]) >> 8
        return out
    for i in range(n):
        out[i] = (base + _upsample_colours(lut[index[i]], height, width)) >> 8
    return out


def heatmap_overlay(
    frame: np.ndarray,
    attn_map: np.ndarray,
    vmin: float | None = None,
    vmax: float | None = None,
    alpha: float = 0.5,
    cmap: str = "viridis",
    interpolation: str = "nearest",
) -> np.ndarray:
    """frame (H, W, 3) uint8, attn_map (rows, cols) -> (H, W, 3) uint8 overlay in the frame's orientation.

    The map is coloured with [vmin, vmax] (default: the map's own range), enlarged to the frame
    (`interpolation`, see heatmap_overlays) and alpha-blended over it (alpha = weight of the heatmap).
    """
    return heatmap_overlays(frame, np.asarray(attn_map)[None], vmin, vmax, alpha, cmap, interpolation)[0]


def mask_bbox(mask: np.ndarray | None) -> tuple[int, int, int, int] | None:
    """mask (H, W) bool -> (top, left, bottom, right) pixel box around its True pixels (bottom/right exclusive), or None."""
    if mask is None:
        return None
    mask = np.asarray(mask, dtype=bool)
    ys = np.flatnonzero(mask.any(axis=1))
    if ys.size == 0:
        return None
    xs = np.flatnonzero(mask.any(axis=0))
    return int(ys[0]), int(xs[0]), int(ys[-1]) + 1, int(xs[-1]) + 1


def _colorbar(height: int, cmap: str) -> np.ndarray:
    """(height, COLORBAR_WIDTH, 3) uint8 vertical colour bar, hottest at the top."""
    ramp = np.linspace(255, 0, height).round().astype(np.uint8)
    return np.repeat(colormap_lut(cmap)[ramp][:, None, :], COLORBAR_WIDTH, axis=1)


def _fmt(value: float) -> str:
    return f"{value:.3g}"


def _draw_box(draw: ImageDraw.ImageDraw, box, top: int, left: int, sy: float, sx: float) -> None:
    y0, x0, y1, x1 = box
    draw.rectangle(
        [left + int(x0 * sx), top + int(y0 * sy), left + int(np.ceil(x1 * sx)) - 1, top + int(np.ceil(y1 * sy)) - 1],
        outline=BOX,
        width=2,
    )


def layer_panel(
    frames: dict[str, np.ndarray],
    maps: dict[str, np.ndarray],
    caption: dict,
    ranges: dict[str, tuple[float, float]] | None = None,
    boxes: dict[str, tuple[int, int, int, int] | None] | None = None,
    head_fusion: str = "mean",
    cmap: str = "viridis",
    alpha: float = 0.5,
    min_cell: int = 128,
    interpolation: str = "nearest",
) -> np.ndarray:
    """One step and layer: rows = cameras, columns = head 0..H-1 then the fused head.

    frames: observation key -> (h, w, 3) uint8 frame the model saw.
    maps: observation key -> (heads, rows, cols) attention of this layer over that camera's patches.
    caption: {"task", "step", "layer"} and optionally "note" (e.g. a random-model warning).
    ranges: observation key -> (vmin, vmax) colour range (per-episode normalisation); default is
      this step's min / max over the row's heads and fused map (per-frame normalisation).
    boxes: observation key -> (top, left, bottom, right) in that frame's pixels (target bounding box).
    min_cell: frames are shown at their own size, enlarged by an integer factor (pixel repetition)
      until at least `min_cell` pixels high, so small model inputs stay legible and patches stay sharp.
    interpolation: how maps are enlarged to the frames (heatmap_overlays). Returns (H, W, 3) uint8.
    """
    if not maps:
        raise ValueError("layer_panel needs at least one camera map")
    heads = int(np.asarray(next(iter(maps.values()))).shape[0])
    stacks = {}
    for cam, m in maps.items():
        cam_maps = np.asarray(m, dtype=np.float32)  # (heads, rows, cols)
        if cam_maps.ndim != 3 or cam_maps.shape[0] != heads:
            raise ValueError(f"maps[{cam!r}] must be (heads={heads}, rows, cols); got {cam_maps.shape}")
        stacks[cam] = np.concatenate([cam_maps, fuse_heads(cam_maps, head_fusion, axis=0)[None]])  # (heads + 1, r, c)
    title = f"{caption.get('task', '')} | step {caption.get('step', '?')} | layer {caption.get('layer', '?')}"
    columns = [f"head {h}" for h in range(heads)] + [head_fusion]
    return _grid_panel(frames, stacks, columns, title, caption.get("note"), ranges, boxes, False, cmap, alpha, min_cell,
                       interpolation)


def attribution_panel(
    frames: dict[str, np.ndarray],
    maps: dict[str, dict[str, np.ndarray]],
    caption: dict,
    boxes: dict[str, tuple[int, int, int, int] | None] | None = None,
    cmap: str = "viridis",
    alpha: float = 0.5,
    min_cell: int = 128,
    interpolation: str = "nearest",
) -> np.ndarray:
    """One step: rows = cameras, columns = attribution methods (`harness.measures.attribution`).

    maps: method -> observation key -> (rows, cols) scores on that camera's patch grid. Methods have
    unrelated units (attention mass, gradient magnitudes, action change), so each cell is coloured
    from its own minimum to its own maximum: compare where each method puts its mass, not its values.
    A camera a method has no map for is left blank. Other arguments as `layer_panel`. Returns (H, W, 3) uint8.
    """
    methods = list(maps)
    cameras = list(dict.fromkeys(cam for m in methods for cam in maps[m]))
    if not cameras:
        raise ValueError("attribution_panel needs at least one method with a camera map")
    stacks = {}
    for cam in cameras:
        grids = {m: np.asarray(maps[m][cam], np.float32) for m in methods if cam in maps[m]}
        shape = next(iter(grids.values())).shape
        if any(g.ndim != 2 or g.shape != shape for g in grids.values()):
            raise ValueError(f"every method's map of {cam!r} must be one (rows, cols) grid; got "
                             f"{[g.shape for g in grids.values()]}")
        stacks[cam] = np.stack([grids.get(m, np.full(shape, np.nan)) for m in methods])  # (methods, rows, cols)
    title = f"{caption.get('task', '')} | step {caption.get('step', '?')} | attribution (each map min..max)"
    return _grid_panel(frames, stacks, methods, title, caption.get("note"), None, boxes, True, cmap, alpha, min_cell,
                       interpolation)


def _grid_panel(frames, stacks, columns, title, note, ranges, boxes, per_cell, cmap, alpha, min_cell,
                interpolation="nearest") -> np.ndarray:
    """Rows = cameras, columns = `columns`; stacks: observation key -> (columns, rows, cols) maps.

    per_cell: colour each cell over its own range (a NaN cell shows the bare frame); otherwise one range
    per row (`ranges[cam]`, or the row's min / max), printed beside the row with a colour bar.
    """
    cameras = list(stacks)
    missing = [c for c in cameras if c not in frames]
    if missing:
        raise ValueError(f"no frame for camera(s) {missing}; pass a frame for every camera with a map")
    font = _font(13)
    small = _font(11)
    line = 17

    sizes = {}
    for c in cameras:
        h, w = frames[c].shape[:2]
        k = max(1, -(-min_cell // h))
        sizes[c] = (h * k, w * k)
    column_width = max(w for _, w in sizes.values()) + PAD  # common pitch; narrower frames are centred
    left = PAD
    bar_left = left + len(columns) * column_width + PAD
    width = bar_left + COLORBAR_WIDTH + 60
    title_h = 3 * line + PAD
    row_tops = np.cumsum([0] + [line + sizes[c][0] + PAD for c in cameras])
    height = title_h + int(row_tops[-1]) + PAD
    canvas = np.full((height, width, 3), BACKGROUND, np.uint8)

    labels = [((left, 2), title, font)]  # (xy, text, font)
    rects = []  # (box, top, left, sy, sx)
    if note:
        labels.append(((left, 2 + line), str(note), font))
    for k, name in enumerate(columns):  # column titles, under the caption
        labels.append(((left + k * column_width, 2 + 2 * line), name, font))
    for r, cam in enumerate(cameras):
        frame = _check_frame(frames[cam])
        stack = stacks[cam]
        ch, cw = sizes[cam]
        shown = resize_nearest(frame, ch, cw)
        top = title_h + int(row_tops[r]) + line
        if per_cell:
            overlays = [shown if not np.isfinite(m).any() else
                        heatmap_overlays(shown, m[None], float(np.nanmin(m)), float(np.nanmax(m)), alpha, cmap,
                                         interpolation)[0]
                        for m in stack]
            labels.append(((left, top - line + 2), cam, small))
            low, high = "min", "max"
        else:
            if ranges is not None and cam in ranges:
                vmin, vmax = ranges[cam]
            else:
                vmin, vmax = float(stack.min()), float(stack.max())
            overlays = heatmap_overlays(shown, stack, vmin, vmax, alpha, cmap, interpolation)  # (columns, ch, cw, 3)
            labels.append(((left, top - line + 2), f"{cam}   range [{_fmt(vmin)}, {_fmt(vmax)}]", small))
            low, high = _fmt(vmin), _fmt(vmax)
        box = (boxes or {}).get(cam)
        for k, overlay in enumerate(overlays):
            x = left + k * column_width + (column_width - PAD - cw) // 2
            canvas[top : top + ch, x : x + cw] = overlay
            if box is not None:
                rects.append((box, top, x, ch / frame.shape[0], cw / frame.shape[1]))
        canvas[top : top + ch, bar_left : bar_left + COLORBAR_WIDTH] = _colorbar(ch, cmap)
        labels.append(((bar_left + COLORBAR_WIDTH + 3, top), high, small))
        labels.append(((bar_left + COLORBAR_WIDTH + 3, top + ch - 13), low, small))

    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    for rect in rects:
        _draw_box(draw, *rect)
    for xy, text, f in labels:
        draw.text(xy, text, fill=TEXT, font=f)
    return np.asarray(image)


def _round_up(n: int, multiple: int) -> int:
    return -(-n // multiple) * multiple


def video_frame(
    frame: np.ndarray | Sequence[np.ndarray],
    overlay: np.ndarray | Sequence[np.ndarray],
    layer_strip_maps: np.ndarray | Sequence[np.ndarray],
    captions: Sequence[str],
    cmap: str = "viridis",
    alpha: float = 0.5,
    display: int = 256,
    strip_columns: int = 6,
    box: tuple[int, int, int, int] | None | Sequence[tuple[int, int, int, int] | None] = None,
    labels: Sequence[str] = (),
    interpolation: str = "nearest",
) -> np.ndarray:
    """One video frame: one row per camera, [camera frame | attention overlay | text] above a strip of per-layer overlays.

    frame, overlay: (h, w, 3) uint8 per camera row (a single array: one row; overlay e.g. from heatmap_overlay on
      that frame); shown at `display` pixels high (nearest neighbour). The first row's frame fills the top-left
      `display` x w pixels (harness.report.build reads it back from there).
    layer_strip_maps: (layers, rows, cols) per camera row, one (fused-head) map per layer, each coloured with its own
      range (`interpolation` as heatmap_overlays).
    captions: text lines (step, action, success, ...) beside the first row, wrapped; labels: the text beside each
      further row (e.g. which camera and map it shows).
    box: optional (top, left, bottom, right) target box in frame pixels per row, drawn on the overlay.
    The size depends only on the frame sizes, the number of cameras and of layers (constant for an episode) and
    is padded to multiples of 16 so video encoders need no resampling. Returns (H, W, 3) uint8.
    """
    one = isinstance(frame, np.ndarray) and frame.ndim == 3
    frames = [_check_frame(f) for f in ([frame] if one else frame)]
    overlays = [_check_frame(o) for o in ([overlay] if one else overlay)]
    strips = [np.asarray(m, dtype=np.float32) for m in ([layer_strip_maps] if one else layer_strip_maps)]
    boxes = [box] if one else list(box or [None] * len(frames))
    if not frames or not len(frames) == len(overlays) == len(strips) == len(boxes):
        raise ValueError(f"video_frame needs one overlay, strip and box per camera row; got {len(frames)} frames, "
                         f"{len(overlays)} overlays, {len(strips)} strips, {len(boxes)} boxes")
    shapes, row_heights, height, width = _video_rows(frames, strips, display, strip_columns)
    canvas = np.full((height, width, 3), BACKGROUND, np.uint8)
    dh = display

    strip_labels, rects, texts = [], [], []  # (x, y, layer), (box, top, left, sy, sx), (x, y, lines)
    top = 0
    for r, (f, o, m, (h, w, dw, thumb_w, thumb_h, ncol, _)) in enumerate(zip(frames, overlays, strips, shapes)):
        canvas[top : top + dh, :dw] = resize_nearest(f, dh, dw)
        canvas[top : top + dh, dw + PAD : 2 * dw + PAD] = resize_nearest(o, dh, dw)
        thumbs = heatmap_overlays(resize_nearest(f, thumb_h, thumb_w), m, alpha=alpha, cmap=cmap,
                                  interpolation=interpolation)  # (layers, th, tw, 3)
        for i in range(m.shape[0]):
            y = top + dh + PAD + (i // ncol) * (thumb_h + PAD)
            x = (i % ncol) * (thumb_w + PAD)
            canvas[y : y + thumb_h, x : x + thumb_w] = thumbs[i]
            strip_labels.append((x, y, i))
        if boxes[r] is not None:
            rects.append((boxes[r], top, dw + PAD, dh / h, dw / w))
        lines = list(captions) if r == 0 else ([labels[r - 1]] if r - 1 < len(labels) else [])
        texts.append((2 * dw + 3 * PAD, top, dw, lines))
        top += row_heights[r]

    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    for rect in rects:
        _draw_box(draw, *rect)
    _draw_video_text(draw, strip_labels, texts, dh)
    return np.asarray(image)


def _video_rows(frames: list[np.ndarray], strips: list[np.ndarray], display: int, strip_columns: int):
    """video_frame's layout: per camera row (h, w, display width, thumb width, thumb height, strip columns, strip
    rows), the rows' heights, and the frame's height and width (padded to multiples of 16)."""
    shapes = []
    dw_max = max(max(1, int(round(display * f.shape[1] / f.shape[0]))) for f in frames)
    top_width = 3 * dw_max + 2 * PAD
    for f, m in zip(frames, strips):
        h, w = f.shape[:2]
        dw = max(1, int(round(display * w / h)))
        ncol = max(1, min(m.shape[0], strip_columns))
        thumb_w = min((top_width - (ncol - 1) * PAD) // ncol, dw // 2)
        shapes.append((h, w, dw, thumb_w, max(1, int(round(thumb_w * h / w))), ncol, -(-m.shape[0] // ncol)))
    row_heights = [display + PAD + nrow * (th + PAD) for _, _, _, _, th, _, nrow in shapes]
    return shapes, row_heights, _round_up(sum(row_heights), 16), _round_up(top_width, 16)


def _draw_video_text(draw: ImageDraw.ImageDraw, strip_labels: list, texts: list, dh: int) -> None:
    """video_frame's text: "layer i" on each strip thumbnail ((x, y, i)), and each row's lines ((x, top, dw, lines))
    wrapped beside it, cut at the row's `dh` pixels."""
    font = _font(13)
    small = _font(11)
    for x, y, i in strip_labels:
        draw.text((x + 3, y + 2), f"layer {i}", fill=(255, 255, 255), font=small, stroke_width=2, stroke_fill=(0, 0, 0))
    for x, top, dw, lines in texts:
        chars = max(8, int((dw - 2 * PAD) / 7))
        y = top + PAD
        for text in lines:
            for piece in textwrap.wrap(str(text), chars) or [""]:
                if y + 16 > top + dh:
                    break
                draw.text((x, y), piece, fill=TEXT, font=font)
                y += 16

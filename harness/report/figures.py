"""Report figures: matplotlib (Agg, no pyplot state) and numpy composites, each returned as PNG bytes.

Inputs are plain arrays already aggregated (harness.analysis.aggregate); nothing here reads run folders.
Several runs share one figure with one colour per run (`run_colours`). NaN means "absent" and is drawn as
such (grey cells marked n/a, gaps in lines), never as zero.
"""

from __future__ import annotations

import io
from typing import Sequence

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize, TwoSlopeNorm
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator
from PIL import Image, ImageDraw, ImageFont

from harness.outputs.overlays import heatmap_overlays

RUN_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22")
DPI = 80
ABSENT_GREY = "#d9d9d9"


def run_colours(n: int) -> list[str]:
    """One colour per run, in order (cycles after 10)."""
    return [RUN_COLOURS[i % len(RUN_COLOURS)] for i in range(n)]


def _figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), dpi=DPI)  # no layout engine: it costs more than the drawing; bbox "tight" trims
    FigureCanvasAgg(fig)
    return fig


def _margins(fig: Figure, left: float, right: float, bottom: float, top: float, **spacing) -> None:
    """Fixed margins in inches (instead of a layout engine or a tight bbox, which draw the figure twice)."""
    width, height = fig.get_size_inches()
    fig.subplots_adjust(left=left / width, right=1 - right / width, bottom=bottom / height, top=1 - top / height, **spacing)


def _png(fig: Figure) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI)
    return buffer.getvalue()


def _short(text: str, n: int = 18) -> str:
    return text if len(text) <= n else text[: n - 1] + "…"


def success_chart(tasks: Sequence[str], series: Sequence[tuple[str, str, dict]]) -> bytes:
    """Success rate per task with intervals; series: [(run label, colour, {task: (rate, low, high, n)})].

    Each task's group holds a bar for each run that holds the task (a run without it draws nothing there, so runs of
    different tasks leave no empty slots); n stands above each bar (a slot is 0.45 in, wider than "n=1000" at 7 pt)."""
    groups = [[i for i, (_, _, data) in enumerate(series) if t in data] for t in tasks]
    slots = sum(max(1, len(g)) for g in groups)
    gap = 0.6  # between task groups, in bar slots
    fig = _figure(max(5.0, 0.45 * (slots + gap * len(tasks)) + 1.2), 3.6)
    ax = fig.add_subplot()
    centres, cursor, drawn = [], 0.0, set()
    for t, group in zip(tasks, groups):
        width = max(1, len(group))
        centres.append(cursor + width / 2 - 0.5)
        for j, i in enumerate(group):
            label, colour, data = series[i]
            rate, low, high, n = (np.nan if v is None else float(v) for v in data[t])
            pos = cursor + j
            ax.bar(pos, rate if np.isfinite(rate) else 0.0, 0.85, color=colour, alpha=0.75,
                   label=label if i not in drawn else None)
            drawn.add(i)
            if np.isfinite(rate) and np.isfinite(low) and np.isfinite(high):
                ax.errorbar([pos], [rate], yerr=[[rate - low], [high - rate]], fmt="none", ecolor="black", capsize=3, lw=1)
            top = high if np.isfinite(high) else (rate if np.isfinite(rate) else 0.0)
            text = "n=0" if not np.isfinite(n) or n == 0 else f"n={int(n)}"
            ax.text(pos, top + 0.02, text, ha="center", va="bottom", fontsize=7)
        cursor += width + gap
    ax.set_xticks(centres, [_short(t) for t in tasks], rotation=90, fontsize=8)
    ax.set_xlim(-0.5 - gap / 2, cursor - gap / 2 - 0.5)
    ax.set_ylim(0, 1.2)
    ax.set_ylabel("success rate (95% Wilson)")
    ax.grid(axis="y", alpha=0.3)
    _margins(fig, 0.7, 0.15, 1.3, 0.45)
    if len(series) > 1:
        ax.legend(fontsize=8, loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=min(4, len(series)), frameon=False)
    return _png(fig)


def _annotated_heatmap(ax, matrix: np.ndarray, norm, cmap: str, annotate: bool):
    masked = np.ma.masked_invalid(matrix)
    cm = matplotlib.colormaps[cmap].copy()
    cm.set_bad(ABSENT_GREY)
    im = ax.imshow(masked, aspect="auto", cmap=cm, norm=norm, interpolation="nearest")
    rows, cols = matrix.shape
    for r in range(rows):
        for c in range(cols):
            v = matrix[r, c]
            if not np.isfinite(v):
                ax.text(c, r, "n/a", ha="center", va="center", fontsize=6, color="#555555")
            elif annotate:
                ax.text(c, r, f"{v:.2g}", ha="center", va="center", fontsize=6, color="black")
    return im


def _lift_norm(matrices: Sequence[np.ndarray]) -> TwoSlopeNorm:
    """Colour scale centred on 1 (chance): blue below, red above."""
    values = np.concatenate([np.ravel(m) for m in matrices]) if matrices else np.array([])
    values = values[np.isfinite(values)]
    vmax = max(1.5, float(np.percentile(values, 99))) if values.size else 2.0
    return TwoSlopeNorm(vmin=0.0, vcenter=1.0, vmax=vmax)


def _held(tasks: Sequence[str], matrices: Sequence[np.ndarray]) -> list[list[int]]:
    """Per task, the indices of the matrices (one per run, rows = tasks) whose row for it holds a value."""
    return [[i for i, m in enumerate(matrices) if np.isfinite(m[r]).any()] for r in range(len(tasks))]


def _every_run_holds_every_task(held: list[list[int]], n: int) -> bool:
    return all(len(h) in (0, n) for h in held)


def task_layer_heatmaps(tasks: Sequence[str], panels: Sequence[tuple[str, str, np.ndarray]], label: str) -> bytes:
    """Target lift per task x layer; panels: [(run label, colour, (tasks, layers))].

    When every run holds every task: one panel per run, a row per task. Otherwise (runs of different tasks): one panel
    per task that has data, a row per run that holds it, so no panel is a wall of absent cells. Tasks without data in
    any run are left out."""
    held = _held(tasks, [m for _, _, m in panels])
    kept = [r for r, h in enumerate(held) if h]
    layers = max((m.shape[1] for _, _, m in panels), default=1)
    if _every_run_holds_every_task(held, len(panels)):
        n = max(1, len(panels))
        fig = _figure(min(22.0, n * (1.6 + 0.38 * layers) + 1.6), 1.0 + 0.3 * len(kept) + 0.6)
        _margins(fig, 1.4, 0.5, 0.6, 0.35, wspace=0.08)
        for i, ax, matrix in _lift_panels(fig, [(r, c, m[kept]) for r, c, m in panels], label):
            ax.set_xlabel("layer")
            ax.set_yticks(range(len(kept)), [_short(tasks[r]) for r in kept] if i == 0 else [""] * len(kept), fontsize=8)
        return _png(fig)
    by_task = [(_short(tasks[r], 24), "black", np.stack([panels[i][2][r] for i in held[r]])) for r in kept]
    cols = min(3, len(by_task))
    rows = -(-len(by_task) // cols)
    panel_w, label_w = 0.4 + 0.36 * layers, 1.5
    height = max(0.3 * max(len(h) for h in held) + 0.35, 0.9)
    fig = _figure(cols * (panel_w + label_w) + 1.2, rows * (height + 0.9) + 0.2)
    _margins(fig, label_w, 1.2, 0.55, 0.35, wspace=label_w / panel_w, hspace=0.9 / height)
    for i, ax, matrix in _lift_panels(fig, by_task, label, grid=(rows, cols)):
        runs = [panels[j] for j in held[kept[i]]]
        ax.set_yticks(range(len(runs)), [_short(run, 16) for run, _, _ in runs], fontsize=8)
        for tick, (_, colour, _) in zip(ax.get_yticklabels(), runs):
            tick.set_color(colour)
        ax.set_xlabel("layer", fontsize=8)
    return _png(fig)


def _lift_panels(fig, panels: Sequence[tuple[str, str, np.ndarray]], label: str, grid: tuple[int, int] | None = None):
    """Lift heatmaps side by side, or on a (rows, cols) grid (shared norm centred on 1, one colour bar, titles in their
    colour, column indices as x ticks); yields (index, axes, matrix) for each panel's own labels before the bar is
    added."""
    rows, cols = grid or (1, max(1, len(panels)))
    norm = _lift_norm([m for _, _, m in panels])
    im = None
    for i, (title, colour, matrix) in enumerate(panels):
        ax = fig.add_subplot(rows, cols, i + 1)
        im = _annotated_heatmap(ax, matrix, norm, "RdBu_r", annotate=matrix.size <= 60)
        ax.set_title(_short(title, 24), color=colour, fontsize=10, fontweight="bold")
        ax.set_xticks(range(matrix.shape[1]), [str(c) for c in range(matrix.shape[1])], fontsize=7)
        yield i, ax, matrix
    if im is not None:
        fig.colorbar(im, ax=fig.axes, shrink=0.8, label=label)


def shares_heatmaps(tasks: Sequence[str], categories: Sequence[str], panels: Sequence[tuple[str, str, dict]]) -> bytes:
    """Modality shares in [0, 1], a column of panels per category; panels: [(run label, colour, {category: (tasks,
    layers)})].

    When every run holds every task: a row of panels per run, each a task x layer heatmap. Otherwise (runs of
    different tasks): a row of panels per task that has data, each a run x layer heatmap of the runs that hold it."""
    matrices = [next(iter(d.values())) if d else np.full((len(tasks), 1), np.nan) for _, _, d in panels]
    held = _held(tasks, matrices)
    kept = [r for r, h in enumerate(held) if h]
    layers = max((m.shape[1] for _, _, d in panels for m in d.values()), default=1)
    if _every_run_holds_every_task(held, len(panels)):
        grid = [(run, colour, [_short(tasks[r], 14) for r in kept], [tasks[r] for r in kept], len(kept),
                 {c: m[kept] for c, m in data.items()}, [None] * len(kept)) for run, colour, data in panels]
    else:  # one row of panels per task: its rows are the runs that hold it
        grid = []
        for r in kept:
            runs = [panels[i] for i in held[r]]
            data = {c: np.stack([d[c][r] if c in d else np.full(layers, np.nan) for _, _, d in runs]) for c in categories}
            grid.append((_short(tasks[r], 20), "black", [_short(run, 12) for run, _, _ in runs], None, len(runs), data,
                         [colour for _, colour, _ in runs]))
    rows, cols = max(1, len(grid)), max(1, len(categories))
    height = max(g[4] for g in grid) if grid else 1
    panel_w, panel_h = max(1.3, 0.6 + 0.17 * layers), max(0.9, 0.45 + 0.17 * height)
    fig = _figure(1.7 + cols * panel_w * 1.12 + 1.0, 0.5 + rows * panel_h * 1.3 + 0.3)
    norm = Normalize(0.0, 1.0)
    im = None
    for r, (name, colour, ylabels, _, n_rows, data, tick_colours) in enumerate(grid):
        for c, category in enumerate(categories):
            ax = fig.add_subplot(rows, cols, r * cols + c + 1)
            matrix = data.get(category)
            if matrix is None:
                matrix = np.full((n_rows, layers), np.nan)
            im = _annotated_heatmap(ax, matrix, norm, "viridis", annotate=False)
            if r == 0:
                ax.set_title(category, fontsize=8)
            if c == 0 and rows > 1:
                ax.set_ylabel(name, color=colour, fontsize=9, fontweight="bold")
            ax.set_yticks(range(n_rows), ylabels if c == 0 else [""] * n_rows, fontsize=7)
            if c == 0:
                for tick, tick_colour in zip(ax.get_yticklabels(), tick_colours):
                    if tick_colour:
                        tick.set_color(tick_colour)
            step = 1 if matrix.shape[1] <= 6 else 3
            ticks = list(range(0, matrix.shape[1], step))
            ax.set_xticks(ticks, [str(i) for i in ticks], fontsize=6)
            if r == rows - 1:
                ax.set_xlabel("layer", fontsize=8)
    _margins(fig, 1.7, 1.0, 0.5, 0.3, hspace=0.3, wspace=0.12)
    if im is not None:
        fig.colorbar(im, ax=fig.axes, shrink=0.8, label="share of attention", fraction=0.03)
    return _png(fig)


def _band(ax, x, mean, low, high, colour, label, style="-"):
    mean, low, high = (np.asarray(a, float) for a in (mean, low, high))
    ax.plot(x, mean, style, color=colour, lw=1.6, label=label, marker="o", ms=2.5)
    ok = np.isfinite(low) & np.isfinite(high)
    if ok.any():
        ax.fill_between(x, np.where(ok, low, np.nan), np.where(ok, high, np.nan), color=colour, alpha=0.18, lw=0)


def progress_small_multiples(
    tasks: Sequence[str],
    series: dict[str, list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]],
    ylabel: str,
    chance: float | None = 1.0,
) -> bytes:
    """One panel per task: a metric along normalised episode progress with interval bands, one line per run.

    series: task -> [(run label, colour, x (bins,), mean, low, high)]; an empty list shows 'absent'."""
    cols = min(5, max(1, len(tasks)))
    rows = -(-len(tasks) // cols) if tasks else 1
    fig = _figure(3.0 * cols + 0.4, 2.3 * rows + 0.6)
    for i, task in enumerate(tasks):
        ax = fig.add_subplot(rows, cols, i + 1)
        lines = series.get(task) or []
        for run, colour, x, mean, low, high in lines:
            _band(ax, x, mean, low, high, colour, run)
        if not lines:
            ax.text(0.5, 0.5, "absent (no target mask)", ha="center", va="center", transform=ax.transAxes, color="#666666")
        if chance is not None:
            ax.axhline(chance, color="black", lw=0.8, ls=":")
        ax.set_title(_short(task, 28), fontsize=9)
        ax.set_xlim(0, 1)
        ax.set_xticks([0.0, 0.5, 1.0])  # fixed ticks: automatic ones are most of the drawing time of 13 panels
        ax.yaxis.set_major_locator(MaxNLocator(4))
        ax.grid(alpha=0.25)
        if i % cols == 0:
            ax.set_ylabel(ylabel, fontsize=8)
        if i >= len(tasks) - cols:
            ax.set_xlabel("episode progress", fontsize=8)
        ax.tick_params(labelsize=7)
    legend = any(len(v) > 1 for v in series.values())
    _margins(fig, 0.65, 0.15, 0.6, 0.8 if legend else 0.45, hspace=0.5, wspace=0.28)
    if legend:
        handles, labels = [], []
        for ax in fig.axes:
            for h, l in zip(*ax.get_legend_handles_labels()):
                if l not in labels:
                    handles.append(h)
                    labels.append(l)
        fig.legend(handles, labels, loc="upper center", ncol=min(4, len(labels)), fontsize=8, bbox_to_anchor=(0.5, 1.0),
                   frameon=False)
    return _png(fig)


def progress_by_outcome(
    lines: Sequence[tuple[str, str, str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]], ylabel: str, chance: float | None = 1.0
) -> bytes:
    """One panel: a metric along progress, lines per (run, outcome); lines: [(run, colour, outcome, x, mean, low, high)].
    Outcome 'success' is solid, 'no_success' dashed, 'all' dotted."""
    fig = _figure(6.0, 3.0)
    ax = fig.add_subplot()
    styles = {"success": "-", "no_success": "--", "all": ":"}
    names = {"success": "successful", "no_success": "unsuccessful", "all": "all episodes"}
    for run, colour, outcome, x, mean, low, high in lines:
        _band(ax, x, mean, low, high, colour, f"{run}: {names.get(outcome, outcome)}", styles.get(outcome, "-"))
    if not lines:
        ax.text(0.5, 0.5, "absent", ha="center", va="center", transform=ax.transAxes, color="#666666")
    if chance is not None:
        ax.axhline(chance, color="black", lw=0.8, ls=":")
    ax.set_xlim(0, 1)
    ax.set_xlabel("episode progress")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.25)
    _margins(fig, 0.75, 0.15, 0.6, 0.15)
    if lines:
        ax.legend(fontsize=7, loc="best")
    return _png(fig)


def head_layer_maps(panels: Sequence[tuple[str, str, np.ndarray]], label: str) -> bytes:
    """Per run a layer x head map (e.g. target lift per head); panels: [(run label, colour, (layers, heads))]."""
    n = max(1, len(panels))
    heads = max((m.shape[1] for _, _, m in panels), default=1)
    layers = max((m.shape[0] for _, _, m in panels), default=1)
    fig = _figure(min(22.0, n * (1.2 + 0.34 * heads) + 1.4), 0.9 + 0.3 * layers)
    _margins(fig, 0.6, 0.5, 0.6, 0.35, wspace=0.15)
    for i, ax, matrix in _lift_panels(fig, panels, label):
        ax.set_yticks(range(matrix.shape[0]), [str(l) for l in range(matrix.shape[0])], fontsize=7)
        ax.set_xlabel("head")
        if i == 0:
            ax.set_ylabel("layer")
    return _png(fig)


def shares_by_layer(panels: Sequence[tuple[str, str, dict[str, np.ndarray]]], colours: dict[str, str]) -> bytes:
    """Stacked modality shares along layers, one panel per run; panels: [(run, colour, {category: (layers,)})]."""
    n = max(1, len(panels))
    fig = _figure(min(20.0, 4.2 * n + 1.6), 2.8)
    _margins(fig, 0.75, 1.6, 0.6, 0.35, wspace=0.2)
    for i, (run, colour, data) in enumerate(panels):
        ax = fig.add_subplot(1, n, i + 1)
        names = [k for k in data if np.isfinite(data[k]).any()]
        if names:
            layers = np.arange(len(data[names[0]]))
            ax.stackplot(layers, *[np.nan_to_num(data[k]) for k in names], labels=names,
                         colors=[colours.get(k, "#999999") for k in names], alpha=0.85)
            ax.set_xlim(0, max(1, len(layers) - 1))
        ax.set_ylim(0, 1)
        ax.set_title(run, color=colour, fontsize=10)
        ax.set_xlabel("layer")
        if i == 0:
            ax.set_ylabel("share of attention")
    handles, labels = fig.axes[0].get_legend_handles_labels() if fig.axes else ([], [])
    if handles:
        fig.legend(handles, labels, loc="center right", fontsize=8, bbox_to_anchor=(1.0, 0.5), frameon=False)
    return _png(fig)


def _font(size: int) -> ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType
        return ImageFont.load_default()


def encode_png(image: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG", optimize=False, compress_level=6)
    return buffer.getvalue()


def overlay_grid(
    frames: Sequence[np.ndarray | None],
    maps: np.ndarray,
    layers: Sequence[int],
    steps: Sequence[int],
    title: str,
    boxes: Sequence[tuple[float, float, float, float] | None] = (),
    cell: int = 96,
    cmap: str = "viridis",
) -> bytes:
    """Layer x time grid of head-mean attention over the camera frame.

    frames: per time column the (h, w, 3) uint8 camera frame, or None (map drawn without a frame);
    maps: (len(layers), len(steps), rows, cols) head-mean attention over the camera's patches, each cell
    coloured with its own range; boxes: per time column the target's (top, left, bottom, right) as fractions
    of the image (drawn in green on every layer), or None. Returns PNG bytes."""
    maps = np.asarray(maps, np.float32)
    n_layers, n_steps, rows, cols = maps.shape
    cell = cell if n_layers <= 6 else cell * 3 // 4  # deep models: smaller cells keep the grid on one screen
    width_cell = max(1, int(round(cell * cols / rows)))
    left, top, pad = 62, 40, 3
    font = _font(12)
    width = max(left + n_steps * (width_cell + pad) + pad, int(font.getlength(title)) + 10)
    canvas = np.full((top + n_layers * (cell + pad) + pad, width, 3), 255, np.uint8)
    for t in range(n_steps):
        frame = frames[t] if t < len(frames) else None
        if frame is not None:  # area-averaged downscale (nearest neighbour would alias the scene)
            base = np.asarray(Image.fromarray(frame).resize((width_cell, cell), Image.BOX))
        else:
            base = np.full((cell, width_cell, 3), 40, np.uint8)
        cells = heatmap_overlays(base, maps[:, t], alpha=0.5 if frame is not None else 1.0, cmap=cmap)
        for li in range(n_layers):
            y = top + li * (cell + pad)
            x = left + t * (width_cell + pad)
            canvas[y:y + cell, x:x + width_cell] = cells[li]
    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    draw.text((4, 3), title, fill=(0, 0, 0), font=font)
    for t, step in enumerate(steps):
        draw.text((left + t * (width_cell + pad) + 2, top - 16), f"step {step}", fill=(0, 0, 0), font=font)
    for li, layer in enumerate(layers):
        draw.text((4, top + li * (cell + pad) + cell // 2 - 7), f"layer {layer}", fill=(0, 0, 0), font=font)
    for t, box in enumerate(boxes):
        if box is None:
            continue
        y0, x0, y1, x1 = box
        x = left + t * (width_cell + pad)
        for li in range(n_layers):
            y = top + li * (cell + pad)
            draw.rectangle([x + int(x0 * width_cell), y + int(y0 * cell), x + max(int(x0 * width_cell) + 1, int(round(x1 * width_cell)) - 1),
                            y + max(int(y0 * cell) + 1, int(round(y1 * cell)) - 1)], outline=(0, 255, 0), width=1)
    return encode_png(np.asarray(image))


def deletion_heatmaps(panels: list[tuple[str, dict]], methods: list[str]) -> bytes:
    """PNG of one heatmap per (task, {(method, camera): deletion AUC / random}) side by side: methods (rows, in the
    given order) x cameras (columns), n/a where absent, colours centred on 1 (random) and clipped to 0.5..1.5, one
    colour bar (the Faithfulness section's figure)."""
    fig = Figure(figsize=(1.4 + 2.2 * len(panels), 1.2 + 0.34 * len(methods)), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    im = None
    for i, (ax, (task, cells)) in enumerate(zip(axes, panels)):
        cameras = sorted({camera for _, camera in cells})
        grid = np.full((len(methods), len(cameras)), np.nan)
        for (method, camera), value in cells.items():
            grid[methods.index(method), cameras.index(camera)] = value
        im = ax.imshow(np.ma.masked_invalid(grid), cmap="RdBu_r", norm=TwoSlopeNorm(1.0, 0.5, 1.5), aspect="auto")
        for (y, x), v in np.ndenumerate(grid):
            ax.text(x, y, "n/a" if not np.isfinite(v) else f"{v:.2f}", ha="center", va="center", fontsize=8)
        ax.set_xticks(range(len(cameras)), [c.removeprefix("image_") for c in cameras])
        ax.set_yticks(range(len(methods)), methods)
        ax.set_title(task, fontsize=9)
        if i:  # the same rows in every panel: labelled once, on the left
            ax.tick_params(labelleft=False)
    fig.suptitle("deletion AUC / random map's (1 = random, > 1: deleting the top-ranked patches moves the action sooner)",
                 fontsize=8)
    fig.colorbar(im, ax=list(axes), fraction=0.03)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight")
    return buffer.getvalue()

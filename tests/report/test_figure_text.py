"""Every figure of the report's cross-task page and task sections, drawn from plain arrays for runs that hold
different tasks (and long run names): no two texts a figure draws intersect (extents taken at draw time), and no panel
is a wall of absent ("n/a") cells."""

import numpy as np

from harness.report import figures
from tests.report.text_overlap import drawn_texts, overlaps

TASKS = ["Lift", "Stack", "PickPlaceCan", "libero_object_pick_up_the_alphabet_soup"]
RUNS = [("lift", "#1f77b4", [0]), ("stack-and-can", "#d62728", [1, 2]),
        ("octo-reference-robosuite-64px-lift", "#2ca02c", [0]), ("libero", "#9467bd", [3])]
LAYERS = 12
CATEGORIES = ["primary", "wrist", "language", "readout", "earlier timesteps"]


def _matrix(rows, rng, scale=2.0):
    m = np.full((len(TASKS), LAYERS), np.nan)
    m[rows] = rng.random((len(rows), LAYERS)) * scale
    return m


def _every_figure():
    rng = np.random.default_rng(0)
    success = [(name, colour, {TASKS[r]: (0.5, 0.2, 0.8, 12) if r else (np.nan, np.nan, np.nan, 0) for r in rows})
               for name, colour, rows in RUNS]
    lift = [(name, colour, _matrix(rows, rng)) for name, colour, rows in RUNS]
    shares = [(name, colour, {c: _matrix(rows, rng, 1.0) for c in CATEGORIES}) for name, colour, rows in RUNS]
    x = (np.arange(10) + 0.5) / 10
    band = lambda: (rng.random(10), rng.random(10) * 0.5, rng.random(10) + 0.5)  # noqa: E731
    progress = {TASKS[r]: [(name, colour, x, *band())] for name, colour, rows in RUNS for r in rows}
    yield "success", figures.success_chart(TASKS, success)
    yield "lift", figures.task_layer_heatmaps(TASKS, lift, "target lift (1 = chance)")
    yield "lift, every run every task", figures.task_layer_heatmaps(
        TASKS, [(n, c, _matrix([0, 1, 2, 3], rng)) for n, c, _ in RUNS], "target lift (1 = chance)")
    yield "shares", figures.shares_heatmaps(TASKS, CATEGORIES, shares)
    yield "progress", figures.progress_small_multiples(TASKS, progress, "target lift, last layer")
    yield "heads", figures.head_layer_maps([(n, c, rng.random((LAYERS, 8)) * 2) for n, c, _ in RUNS[:2]], "lift")
    yield "outcome", figures.progress_by_outcome([(n, c, "success", x, *band()) for n, c, _ in RUNS[:2]], "lift")
    yield "shares by layer", figures.shares_by_layer(
        [(n, c, {k: rng.random(LAYERS) / 5 for k in CATEGORIES}) for n, c, _ in RUNS[:3]], {})


def test_no_figure_draws_text_over_text_and_no_panel_of_absent_cells():
    with drawn_texts() as texts:
        names = [name for name, png in _every_figure() if png[:4] == b"\x89PNG"]
    assert len(names) == len(texts) == 8
    for name, drawn in zip(names, texts.values()):
        assert not overlaps(drawn), (name, overlaps(drawn))
        assert "n/a" not in [t for t, _ in drawn], name
    success = [t for t, _ in list(texts.values())[0]]
    assert success.count("n=12") == 3 and success.count("n=0") == 2  # a bar per run that holds the task, no more


def test_the_overlap_check_can_fail():
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2, 2), dpi=80)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.text(0.5, 0.5, "no episodes")
    ax.text(0.52, 0.5, "no episodes")
    with drawn_texts() as texts:
        fig.canvas.draw()
    assert overlaps(next(iter(texts.values()))) == [("no episodes", "no episodes")]

"""Test helper: the text each matplotlib figure draws, with its window extent taken at draw time, and the pairs of
visible texts whose extents intersect (labels that overlap on the page)."""

from __future__ import annotations

import contextlib
from collections import defaultdict

from matplotlib.text import Text


@contextlib.contextmanager
def drawn_texts():
    """Within the block, records every visible, non-empty Text artist matplotlib draws: {id(figure): [(text, bbox)]}
    (tick labels outside the view are never drawn, so they are not recorded)."""
    found: dict[int, list] = defaultdict(list)
    original = Text.draw

    def draw(self, renderer):
        original(self, renderer)
        if self.get_visible() and self.get_text().strip() and self.figure is not None:
            found[id(self.figure)].append((self.get_text(), self.get_window_extent(renderer).frozen()))

    Text.draw = draw
    try:
        yield found
    finally:
        Text.draw = original


def overlaps(texts: list, tolerance: float = 1.0) -> list[tuple[str, str]]:
    """Pairs of texts whose extents intersect by more than `tolerance` pixels in both directions."""
    out = []
    for i, (a, box_a) in enumerate(texts):
        for b, box_b in texts[i + 1:]:
            dx = min(box_a.x1, box_b.x1) - max(box_a.x0, box_b.x0)
            dy = min(box_a.y1, box_b.y1) - max(box_a.y0, box_b.y0)
            if dx > tolerance and dy > tolerance:
                out.append((a, b))
    return out

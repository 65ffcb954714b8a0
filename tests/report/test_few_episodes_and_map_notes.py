"""Report text that says what it can support (issue 43 items 4 and 5): faithfulness rows from fewer than 4 episodes get
no collapsed interval, and the robustness section says which attention map its figures use."""

from __future__ import annotations

from types import SimpleNamespace

from harness.report import faithfulness, robustness


def test_fewer_than_four_episodes_get_no_interval():
    assert faithfulness._ci_text(1.9, 1.75, 2.05, 2) == "1.90 (too few episodes for an interval)"
    assert faithfulness._ci_text(1.9, 1.75, 2.05, 3) == "1.90 (too few episodes for an interval)"
    assert faithfulness._ci_text(1.4, 1.29, 1.48, 4) == "1.40 [1.29, 1.48]"
    row = ("run", "Stack", "image_wrist", "occlusion", 9, 2, 0.0, 1.90, 1.75, 2.05, 0.36, 0.30, 0.41, 6.38, 2, "mean",
           0.47, 0.35, 0.59)
    text = faithfulness.sentence("Stack", [row])
    assert "1.90x random (too few episodes for an interval)" in text and "[1.75" not in text
    assert "no verdict against random" in text and "better than random" not in text and "2 episodes" in text
    six = row[:5] + (6,) + row[6:]
    assert "1.90x random [1.75, 2.05]" in faithfulness.sentence("Stack", [six])


def _record(controls):
    return SimpleNamespace(manifest={"protocol": {"policy": {"attention_controls": controls}}})


def test_robustness_section_names_the_map_its_figures_use():
    raw = robustness.map_note([_record(None)])
    assert "raw attention maps" in raw and "may include position-bound attention" in raw
    assert "content-only" in robustness.map_note([_record(None), _record("blank,mirror")])

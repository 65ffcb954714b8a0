"""EVAL.md's "Failure early warning" section (issue 74 item 4; harness/report/early_warning.py): on hand-made
episodes with known answers (a probe fed the labels is better than time and phase; one fed noise is a null result that
says what it could have resolved), the per-phase stall table, the short form (no prose paragraph over 120 words), and
the round trip through its figures file."""

from __future__ import annotations

import functools
import math
import re

import numpy as np

from harness.analysis.diagnose import Diagnosis
from harness.analysis.diagnose.evaluate import evaluate_task
from harness.analysis.diagnose.failures import failure_rows
from harness.report import early_warning as W
from harness.report import figures_file
from tests.analysis.test_diagnose import episodes


@functools.cache
def diagnosis(kind: str, seeds: int = 30) -> Diagnosis:
    made = episodes(kind, seeds=seeds, rng=np.random.default_rng(1))
    result = evaluate_task(made, resamples=300)
    return Diagnosis(["run0", "run1", "run2"], {"Lift": result}, failure_rows(made),
                     settings={"folds": 5, "resamples": 300, "seed": 0, "min_class": 5})


def prose(text: str) -> list[str]:
    """Paragraphs and list items that are not tables or headings."""
    out = []
    for block in re.split(r"\n\s*\n", text):
        for item in re.split(r"\n(?=- )", block):
            if not item.lstrip().startswith(("|", "#")):
                out.append(item)
    return out


def test_a_probe_fed_the_labels_is_named_better_with_its_difference():
    text = W.section_text(diagnosis("labels"), "Made by hand.")
    (line,) = [p for p in prose(text) if p.startswith("Lift: ")]
    assert line.startswith("Lift: better than time and phase: readout probe at t = 10 (+")
    assert "| readout probe | 1.00 [1.00, 1.00], better |" in text


def test_a_probe_fed_noise_is_a_null_result_that_says_what_it_could_have_resolved():
    made = diagnosis("noise")
    text = W.section_text(made, "")
    (line,) = [p for p in prose(text) if p.startswith("Lift: ")]
    assert line.startswith("Lift: no predictor is better than time and phase at any step or phase.")
    width = float(re.search(r"could have resolved is ±([0-9.]+)", line).group(1))
    widths = [W.resolvable(c["predictors"][name]) for c in made.tasks["Lift"]["by_step"] + made.tasks["Lift"]["by_phase"]
              for name in c["predictors"] if name != "time and phase"]
    assert 0 < width == round(min(w for w in widths if math.isfinite(w)), 2) < 1
    table = text.split("Resolvable AUROC difference from time and phase, by step:")[1].split("\n\n")[1]
    assert table.startswith("| predictor | t = 10 | t = 25 | t = 50 | t = 100 |") and "| readout probe | ±" in table


def test_a_zero_width_interval_resolves_nothing():
    assert math.isnan(W.resolvable({"difference_interval": [0.5, 0.5]}))
    assert math.isnan(W.resolvable({"difference_interval": [math.nan, math.nan]}))
    assert abs(W.resolvable({"difference_interval": [-0.2, 0.4]}) - 0.3) < 1e-12


def test_the_stall_table_counts_every_failure_once_by_its_phase():
    made = diagnosis("noise")
    lines = W.stall_table(made.failures, "Lift", made.tasks["Lift"]["phases"])
    rows = [line.split(" | ") for line in lines[2:]]
    assert sum(int(r[1]) for r in rows) == len(made.failures) > 0
    assert [r[0].strip("| ") for r in rows] == [p for p in made.tasks["Lift"]["phases"]
                                                 if any(f["furthest_phase"] == p for f in made.failures)]


def test_the_section_is_short_form_and_round_trips_through_its_figures_file():
    text = W.section_text(diagnosis("labels"), "Made by `a command`.")
    assert text.startswith(W.SECTION + "\n")
    assert all(len(p.split()) <= 120 for p in prose(text)), max(prose(text), key=lambda p: len(p.split()))
    doc = figures_file.figures(text, "Provenance: here.")
    rendered = figures_file.render(doc)
    assert rendered == text.replace(W.SECTION + "\n\n", W.SECTION + "\n\nProvenance: here.\n\n", 1)
    assert sum("table" in b for b in doc["blocks"]) == 4  # AUROC, resolvable, lead time, stall


def test_a_task_with_too_few_of_a_class_keeps_its_line_and_its_stall_table():
    made = episodes("noise", seeds=30, rng=np.random.default_rng(1))
    few = [e for e in made if not e.success or e.seed < 2]
    line = "Lift: too few successes to predict failure"
    result = Diagnosis(["run0"], {"Lift": {"episodes": len(few), "failures": 3, "seeds": 30, "runs": ["run0"],
                                           "message": line}}, failure_rows(few),
                       settings={"folds": 5, "resamples": 300, "seed": 0, "min_class": 5})
    text = W.section_text(result)
    assert line in text and "Where Lift's failed episodes stalled:" in text and "| predictor |" not in text


def test_a_folder_that_is_no_run_is_one_line_and_exit_2(tmp_path, capsys):
    """Every section command (harness.report.eval_md.section_main): a folder that is no run was a traceback, exit 1."""
    from harness.report import robustness

    eval_md = tmp_path / "EVAL.md"
    eval_md.write_text("# m\n")
    for main in (W.main, robustness.main):
        assert main([str(tmp_path), "--eval-md", str(eval_md)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "is not an octo-harness run folder" in err[0], err
    assert eval_md.read_text() == "# m\n" and not (tmp_path / "figures").exists()


def test_unfinished_runs_are_named_and_their_figures_called_interim():
    text = W.section_text(diagnosis("labels"), "", ["camera-5 (35 of 60 episodes)"])
    assert "- Not finished, so these figures are interim: camera-5 (35 of 60 episodes)." in text
    assert "interim" not in W.section_text(diagnosis("labels"), "")

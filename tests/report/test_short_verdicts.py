"""Generated verdicts in short sentences (issue 67 item 4): compare's provenance sentence becomes one bullet per
part (model numerics, inputs, platform) in compare.md, compare.html and regress's console, and no figure is lost on
the way. Pure text, no runs."""

from __future__ import annotations

import re

from harness.analysis.provenance import summary_points, summary_sentence

NUMBERS = re.compile(r"\d+(?:\.\d+)?(?:e-?\d+)?")


def _sentence(verdict="EQUIVALENT", same=False, other=()):
    platform = {"known": True, "same": same, "differs_in": [] if same else ["cpu.model", "xla_flags"]}
    inputs = {"pairs_with_digests": 8, "pairs": 8, "step0_same": 7, "leading_steps_min": 3, "leading_steps_max": 41}
    numerics = {"verdict": verdict, "action_change_max": 2.5e-05, "attention_js_max": 1.2e-08,
                "tolerances": {"action": 3e-4, "attention_js": 3.5e-7}}
    return summary_sentence(platform, inputs, numerics, {"cause": "the intervention's", "other": list(other)})


def test_the_provenance_sentence_splits_into_its_parts_outside_parentheses():
    sentence = _sentence()
    points = summary_points(sentence)
    assert points == [
        "model numerics at step 0: EQUIVALENT (largest change: action 2.5e-05, tolerance 0.0003; attention JS "
        "1.2e-08 bits, tolerance 3.5e-07)",  # the ';' inside the parentheses does not split it
        "both arms fed the policy identical inputs at step 0 in 7/8 pairs, for 3-41 leading steps",
        "platform: different (cpu.model, xla_flags)",
        "trajectories that diverge after identical step-0 numerics are this float noise amplified by the closed loop, "
        "the platform's, not the model's",
    ]
    assert all(len(p.split()) <= 30 for p in points[:2])
    assert sorted(NUMBERS.findall(sentence)) == sorted(n for p in points for n in NUMBERS.findall(p))


def test_every_figure_of_every_form_of_the_sentence_is_kept():
    for sentence in (_sentence("IDENTICAL", same=True), _sentence("UNKNOWN"),
                     _sentence(other=[{"field": "perturb"}])):
        points = summary_points(sentence)
        assert len(points) >= 3 and all(points)
        assert "; ".join(points) == sentence.rstrip(".")  # nothing added, nothing dropped


def test_the_phase_verdicts_are_short_lines_and_their_figures_are_table_rows():
    from harness.report import phases

    tests = [("run", "Lift", "image_primary", "target", 3, "friedman", 9.1, 0.004, 10, "reach grasp lift", "0.81 1.52 1.10"),
             ("run", "Lift", "image_primary", "gripper", 3, "friedman", 1.2, 0.41, 10, "reach grasp lift", "1.00 1.02 0.97"),
             ("run", "Lift", "image_wrist", "target", 3, "wilcoxon", 2.0, 0.01, 9, "reach grasp", "0.40 0.90")]
    steps = [("run", "Lift", "reach", 10, 10, 12.5, 0, 0), ("run", "Lift", "grasp", 10, 9, 20.0, 2, 2)]
    failures = [("run", "Lift", "grasp", "image_primary", "target", 3, 0.95, 1.61, 0.031, 2, 8)]
    summary = {"tests": tests, "steps": steps, "failures": failures}
    line = phases.sentence("Lift", summary)
    assert line == "Lift, image_primary, layer 3: attention changes across phases for target." and len(line.split()) <= 25
    assert phases.phase_test_rows("Lift", summary) == [
        ("target", "reach 0.81, grasp 1.52, lift 1.10", "Friedman", "0.004", "10", "yes"),
        ("gripper", "reach 1.00, grasp 1.02, lift 0.97", "Friedman", "0.41", "10", "not detectably")]
    assert phases.failure_sentence("Lift", summary) == "Lift: failed episodes stopped in grasp (2)."
    assert phases.failure_rows("Lift", summary) == [("grasp", "0.95", "1.61", "0.031")]


def test_the_position_verdict_is_a_short_line_per_task():
    from harness.report import position

    share = [("run", "Lift", cam, layer, "mean", 40, blank, 0.9, "(1,2)" if flag else "", 0.12 if flag else 0.0)
             for cam in ("image_primary", "image_wrist") for layer, blank, flag in ((0, 0.83, False), (1, 0.97, True))]
    line = position.sentence("Lift", {"share": share})
    assert line == ("Lift: image_primary 83%-97% remains on a blank frame, flagged in 1/2 layers; image_wrist 83%-97% "
                    "remains on a blank frame, flagged in 1/2 layers.") and len(line.split()) <= 25
    assert position.sentence("Stack", {"share": share}) == "Stack: no controls recorded."

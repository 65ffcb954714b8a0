"""compare / regress over robustness grids: every task x condition is a cell of the Holm family, so a candidate
that holds its nominal success but collapses under one condition fails the gate (run folders written by hand)."""

import json

import pytest

from harness import cli
from harness.analysis.compare import compare_grids, exit_code
from harness.analysis.paired import holm_adjust, mcnemar_exact
from tests.analysis.test_compare_outcomes import PROTOCOL, write_run

PERTURB = {"nominal": None, "camera-3": "camera@image_primary:3"}


def write_grid(folder, outcomes: dict[str, dict[str, list]], model="m", runs=None):
    """{run name: {task: [success per episode]}} -> a grid folder with robustness.json (perturb per PERTURB)."""
    folder.mkdir(parents=True)
    for name, successes in outcomes.items():
        protocol = {**PROTOCOL, **({"perturb": PERTURB[name]} if PERTURB[name] else {})}
        write_run(folder / name, successes, protocol=protocol, model=model)
    grid = {"format": "octo-harness-robustness/1", "conditions": ["camera"], "levels": [0, 3],
            "tasks": ["Lift"], "runs": runs if runs is not None else {name: PERTURB[name] for name in outcomes}}
    (folder / "robustness.json").write_text(json.dumps(grid))
    return folder


def test_a_candidate_that_loses_one_condition_fails(tmp_path, capsys):
    base = write_grid(tmp_path / "base", {"nominal": {"Lift": [True] * 12}, "camera-3": {"Lift": [True] * 12}})
    cand = write_grid(tmp_path / "cand", {"nominal": {"Lift": [True] * 12}, "camera-3": {"Lift": [False] * 12}},
                      model="m2")
    result = compare_grids(base, cand)
    cells = result.outcomes.tasks
    assert set(cells) == {"Lift / nominal", "Lift / camera-3"} and result.outcomes.holm_family == 3
    expected = holm_adjust([1.0, mcnemar_exact(12, 0), mcnemar_exact(12, 0)])
    assert cells["Lift / camera-3"].mcnemar_p_holm == pytest.approx(expected[1])
    assert cells["Lift / camera-3"].verdict == "REGRESSED"
    assert cells["Lift / nominal"].verdict in ("IDENTICAL", "HELD", "UNDERPOWERED")
    assert result.verdict == "REGRESSED" and exit_code(result) == 1
    assert cli.main(["compare", str(base), str(cand), "--no-frames"]) == 1
    assert "Lift / camera-3" in capsys.readouterr().out
    assert (cand / "compare_base" / "compare.json").is_file()


def test_the_family_grows_with_tasks_and_conditions(tmp_path):
    outcomes = {"nominal": {"Lift": [True] * 6, "Stack": [True] * 6}, "camera-3": {"Lift": [True] * 6, "Stack": [True] * 6}}
    base = write_grid(tmp_path / "base", outcomes)
    drop = {"nominal": {"Lift": [True] * 6, "Stack": [True] * 6}, "camera-3": {"Lift": [False] * 6, "Stack": [True] * 6}}
    cand = write_grid(tmp_path / "cand", drop, model="m2")
    result = compare_grids(base, cand)
    assert result.outcomes.holm_family == 5  # 2 tasks x 2 conditions + pooled
    # 6 of 6 lost: p = 2/64 alone would pass alpha 0.05, times the family of 5 it cannot: not REGRESSED
    assert result.outcomes.tasks["Lift / camera-3"].mcnemar_p == pytest.approx(2 / 64)
    assert result.outcomes.tasks["Lift / camera-3"].verdict != "REGRESSED"
    assert exit_code(result) == 1  # the interval still shows the drop: SUSPECT fails the default gate


def test_holding_every_condition_passes(tmp_path):
    outcomes = {"nominal": {"Lift": [True] * 30}, "camera-3": {"Lift": [True] * 30}}
    base = write_grid(tmp_path / "base", outcomes)
    cand = write_grid(tmp_path / "cand", outcomes, model="m2")
    result = compare_grids(base, cand)
    assert result.verdict in ("IDENTICAL", "HELD", "UNDERPOWERED") and exit_code(result) == 0


@pytest.mark.parametrize("damage", ["missing_condition", "grid_vs_run", "bad_grid_file", "perturb_mismatch"])
def test_bad_grids_are_one_line_exit_2(tmp_path, capsys, damage):
    outcomes = {"nominal": {"Lift": [True] * 4}, "camera-3": {"Lift": [True] * 4}}
    base = write_grid(tmp_path / "base", outcomes)
    if damage == "missing_condition":
        cand = write_grid(tmp_path / "cand", {"nominal": {"Lift": [True] * 4}}, model="m2")
    elif damage == "grid_vs_run":
        cand = base / "nominal"
    elif damage == "bad_grid_file":
        cand = write_grid(tmp_path / "cand", outcomes, model="m2")
        (cand / "robustness.json").write_text('{"runs": {"../../etc": null}}')
    else:
        cand = write_grid(tmp_path / "cand", outcomes, model="m2")
        (base / "robustness.json").write_text(json.dumps({"runs": {"nominal": None, "camera-3": "lighting:3"}}))
    code = cli.main(["compare", str(base), str(cand), "--no-frames"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err

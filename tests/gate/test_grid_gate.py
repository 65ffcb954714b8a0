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


def test_a_loss_beyond_max_drop_without_significance_is_underpowered_and_passes(tmp_path):
    """2 of 6 lost under one condition: a drop of 33 points, beyond --max-drop 0.1, that neither the exact test nor
    the interval confirms: UNDERPOWERED, exit 0 (docs/perturbations.md, "Gating on conditions"); it fails only with
    --fail-on underpowered."""
    base = write_grid(tmp_path / "base", {"nominal": {"Lift": [True] * 6}, "camera-3": {"Lift": [True] * 6}})
    cand = write_grid(tmp_path / "cand", {"nominal": {"Lift": [True] * 6}, "camera-3": {"Lift": [True] * 4 + [False] * 2}},
                      model="m2")
    result = compare_grids(base, cand)
    cell = result.outcomes.tasks["Lift / camera-3"]
    assert cell.difference < -0.1 and cell.verdict == "UNDERPOWERED" and result.verdict == "UNDERPOWERED"
    assert exit_code(result) == 0 and exit_code(result, "underpowered") == 1


@pytest.mark.parametrize("fail_on", ["changed", "suspect"])
def test_regress_on_a_grid_says_in_one_line_that_fail_on_changed_gates_as_suspect(tmp_path, capsys, monkeypatch,
                                                                                   fail_on):
    """A grid is not replayed on recorded inputs, so `--fail-on changed` gates it as `suspect`; one line on stderr
    says so (docs/regression.md, docs/perturbations.md). The candidate grid is written by hand in place of its runs:
    one pair lost under camera-3 is UNDERPOWERED, which passes as `suspect` and would fail as `changed`."""
    from harness.gate import regress as regress_module
    from harness.gate.results import GRID_FORMAT, RegressGridResult

    base = write_grid(tmp_path / "base", {"nominal": {"Lift": [True] * 6}, "camera-3": {"Lift": [True] * 6}})
    made = {}

    def regress_grid(baseline, model, gate, *, out, run_name=None, executor=None):
        folder = write_grid(out / "cand", {"nominal": {"Lift": [True] * 6}, "camera-3": {"Lift": [True] * 5 + [False]}},
                            model=model)
        compared = compare_grids(baseline, folder, gate.compare(), require_complete=False)
        made["result"] = RegressGridResult(format=GRID_FORMAT, verdict=compared.verdict, conditions={},
                                           compare_verdict=compared.verdict, baseline_grid=str(baseline),
                                           candidate_run=str(folder), compare=compared)
        return made["result"]

    monkeypatch.setattr(regress_module, "regress_grid", regress_grid)
    code = cli.main(["regress", "--baseline", str(base), "--model", "m2", "--out", str(tmp_path / "out"),
                     "--fail-on", fail_on])
    said = [line for line in capsys.readouterr().err.splitlines() if "--fail-on changed" in line]
    assert said == ([regress_module.GRID_FAIL_ON_CHANGED] if fail_on == "changed" else [])
    assert made["result"].verdict == "UNDERPOWERED" and code == 0 == regress_module.exit_code(made["result"], "suspect")
    assert regress_module.exit_code(made["result"], "changed") == 1  # what `changed` itself would have said
    assert json.loads((tmp_path / "out" / "cand" / "regress" / "regress.json").read_text())["exit_code"] == 0

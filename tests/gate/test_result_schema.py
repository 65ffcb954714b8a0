"""The typed gate results write the JSON files the commands always wrote (issue 64, item 3).

tests/gate/examples/ holds files written by the commands before their results were typed: compare.json of the golden
runs (scripts/golden_runs.sh: two Lift runs of the reference policy), and regress.json, its compare.json and replay.json
of a 2-episode Lift run of the tiny fixture against itself. Each is read into its dataclass and written again as
`harness.files.atomic_write_json` writes it: byte for byte the same file. Hand-made runs (no simulator) cover the keys
these examples lack: an INCOMPLETE candidate, errored pairs, a robustness grid.
"""

import json
from pathlib import Path

import pytest

from harness.analysis.compare import compare_grids, compare_runs
from harness.analysis.compare_result import CompareResult, OutcomeBlock, PairDetail, RobustnessGrid
from harness.files import json_safe
from harness.gate.results import RegressResult, ReplayResult
from harness.report.compare_html import write_comparison
from harness.results import ABSENT
from harness.verdicts import GateVerdict, ReplayVerdict
from tests.analysis.test_compare_outcomes import write_run
from tests.gate.test_grid_gate import write_grid

EXAMPLES = Path(__file__).resolve().parent / "examples"
KINDS = {"compare.json": CompareResult, "regress_compare.json": CompareResult, "regress.json": RegressResult,
         "replay.json": ReplayResult}


def written(result) -> str:
    """The file atomic_write_json makes of a typed result."""
    return json.dumps(json_safe(result.to_json()), indent=2, sort_keys=True) + "\n"


@pytest.mark.parametrize("name", sorted(KINDS))
def test_a_committed_example_is_read_and_written_again_byte_for_byte(name):
    text = (EXAMPLES / name).read_text()
    result = KINDS[name].from_json(json.loads(text))
    assert written(result) == text


def test_the_examples_are_read_into_types_not_dicts():
    compare = CompareResult.from_json(json.loads((EXAMPLES / "compare.json").read_text()))
    assert compare.verdict is GateVerdict.IDENTICAL and compare.exit_code == 0 and compare.grid is ABSENT
    block = compare.outcomes.tasks["Lift"]
    assert isinstance(block, OutcomeBlock) and block.paired_verdict is GateVerdict.UNDERPOWERED
    assert block.table.n == block.pairs == 2 and isinstance(compare.pair_details[0], PairDetail)
    assert compare.pair_details[0].derived_difference is ABSENT  # a key the file does not hold stays out of it
    regress = RegressResult.from_json(json.loads((EXAMPLES / "regress.json").read_text()))
    assert regress.verdict is GateVerdict.IDENTICAL and regress.sequential.verdict is GateVerdict.UNDERPOWERED
    assert regress.compare is ABSENT and regress.compare_json.endswith("compare.json")
    assert regress.replay.verdict is ReplayVerdict.EQUIVALENT and regress.replay.episode_details is ABSENT
    replay = ReplayResult.from_json(json.loads((EXAMPLES / "replay.json").read_text()))
    assert replay.verdict is ReplayVerdict.EQUIVALENT and len(replay.episode_details) == replay.episodes == 2
    assert replay.tolerances.action > 0 and replay.first_change is None


def test_an_unknown_key_is_refused_naming_it():
    data = json.loads((EXAMPLES / "replay.json").read_text())
    with pytest.raises(ValueError, match="ReplayResult: unknown key.*surprise"):
        ReplayResult.from_json({**data, "surprise": 1})


def _round_trip(result: CompareResult, folder: Path, code: int) -> dict:
    """compare's files written from `result`, compare.json read back: it writes the same file, and holds what the
    result held (with the exit code beside it)."""
    write_comparison(result, folder, exit_code=code)
    text = (folder / "compare.json").read_text()
    back = CompareResult.from_json(json.loads(text))
    assert written(back) == text
    data = json.loads(text)
    assert data == {**json_safe(result.to_json()), "exit_code": code}
    return data


def test_an_incomplete_candidate_with_errored_pairs_round_trips(tmp_path):
    base = write_run(tmp_path / "base", {"Lift": [True, None, True, True], "Stack": [True, False]})
    cand = write_run(tmp_path / "cand", {"Lift": [True, True, None], "Stack": [True, False]}, model="m2")
    result = compare_runs(base, cand)
    assert result.verdict is GateVerdict.INCOMPLETE and result.incomplete.tasks == {"Lift": 1}
    data = _round_trip(result, tmp_path / "out", 4)
    assert data["incomplete"]["note"].startswith("INCOMPLETE") and data["outcomes"]["notes"][0].startswith("INCOMPLETE")
    assert data["missing_pairs"] == {"candidate": [["Lift", 3]], "baseline": []}
    assert data["outcomes"]["tasks"]["Lift"]["errored_pairs"] == 2
    assert "compared_steps" not in data["pair_details"][0]  # hand-made runs have no arrays: the key stays out


def test_a_grid_comparison_and_its_grid_file_round_trip(tmp_path):
    outcomes = {"nominal": {"Lift": [True] * 6}, "camera-3": {"Lift": [True] * 6}}
    base, cand = write_grid(tmp_path / "base", outcomes), write_grid(tmp_path / "cand", outcomes, model="m2")
    result = compare_grids(base, cand)
    data = _round_trip(result, tmp_path / "out", 0)
    assert data["grid"]["conditions"] == ["nominal", "camera-3"] and data["grid"]["cells"] == 2
    assert [p["condition"] for p in data["pair_details"]] == ["nominal"] * 6 + ["camera-3"] * 6
    grid = json.loads((base / "robustness.json").read_text())
    assert RobustnessGrid.from_json(grid).to_json() == grid

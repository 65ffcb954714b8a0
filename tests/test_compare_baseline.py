"""The harness's regression gate on itself: re-run every committed baseline (results/baselines/<name>/) and compare.

Each baseline holds a small run (manifest, results, step-0 arrays) made by scripts/make_baseline.py. The same
protocol and model run again must give the same outcomes and no regression; on the machine that made the
baseline the comparison is IDENTICAL (every stored array within 1e-6).
"""

import json
import warnings
from pathlib import Path

import pytest

from harness.analysis.compare import compare_runs, exit_code
from harness.run import execute
from harness.run.regress import candidate_protocol

REPO = Path(__file__).resolve().parents[1]
BASELINES = REPO / "results" / "baselines"
NAMES = sorted(p.name for p in BASELINES.glob("*") if (p / "BASELINE.json").is_file())


def _model(ref: str, fixtures_dir: Path) -> str:
    kind, _, rest = ref.partition(":")
    if kind == "repo":
        return str(REPO / rest)
    if kind == "fixture":
        return str(fixtures_dir / rest)
    return ref


def test_there_is_a_committed_baseline():
    assert NAMES, f"no baseline under {BASELINES}; make one with scripts/make_baseline.py"


@pytest.mark.parametrize("name", NAMES)
def test_rerunning_a_committed_baseline_gives_no_regression(name, fixtures_dir, tmp_path):
    folder = BASELINES / name
    info = json.loads((folder / "BASELINE.json").read_text())
    manifest = json.loads((folder / "manifest.json").read_text())
    protocol = candidate_protocol(manifest, _model(info["model_ref"], fixtures_dir))
    summary = execute(protocol, tmp_path, "again", progress=False)
    assert summary.manifest["protocol"]["model_fingerprint"] == info["model_fingerprint"], (
        f"the model of baseline {name} changed; regenerate it (scripts/make_reference_baseline.sh for reference-lift, "
        "else octo-harness run + scripts/make_baseline.py) and commit it")

    result = compare_runs(folder, summary.run_dir)
    assert exit_code(result) == 0, result["verdict"]
    details = result["pair_details"]
    assert len(details) == len(manifest["jobs"]) and not any(result["missing_pairs"].values())
    for pair in details:  # same outcomes, pair by pair
        assert (pair["baseline_success"], pair["baseline_steps"]) == (pair["candidate_success"], pair["candidate_steps"])
    step0 = result["drift"]["step0"]["overall"]
    assert step0["action_max_abs"] <= 1e-4 and step0["js_mean"] <= 1e-4
    if result["verdict"] != "IDENTICAL":  # another CPU may round float16 attention differently
        warnings.warn(f"baseline {name}: near-identical, not IDENTICAL: {result['identical']['first_difference']}")

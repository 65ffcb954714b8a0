"""compare and regress end to end: real simulator, real JAX model (the reference fixture and a perturbed copy).

A run compared with itself is IDENTICAL (exit 0); a different max_steps is refused (exit 2, one line naming
the field); another model gives a non-IDENTICAL verdict with step-0 drift > 0; regress runs the candidate on
the baseline's seeds, resumes without new episodes, and fails on UNDERPOWERED when asked.
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from envs.options import EnvOptions
from harness import cli
from harness.analysis.compare import compare_runs, exit_code
from harness.analysis.compare_result import CompareResult
from harness.files import json_safe
from harness.gate.results import RegressResult
from harness.octo import load_pretrained
from harness.run import Protocol, execute
from harness.outputs.writers import OutputOptions

pytestmark = pytest.mark.slow

STEPS = 2


def read_back(path: Path, kind):
    """A JSON file a command wrote, read back as its typed result; the result writes the file's JSON again, key for
    key (the schema round trip)."""
    data = json.loads(path.read_text())
    result = kind.from_json(data)
    assert json_safe(result.to_json()) == data
    return result


def _perturbed_copy(source: Path, dest: Path) -> Path:
    """The fixture checkpoint with the action head's kernels and one attention query changed (same architecture)."""
    import flax.serialization as serialization

    shutil.copytree(source, dest)
    path = next(dest.glob("*/default/checkpoint"))
    tree = serialization.msgpack_restore(path.read_bytes())
    rng = np.random.default_rng(0)

    def perturb(node, inside):
        for key, value in node.items():
            if isinstance(value, dict):
                perturb(value, inside + (key,))
            elif key == "kernel" and ("heads_action" in inside or "encoderblock_1" in inside):
                node[key] = (value * 1.5 + rng.normal(0, 0.05, value.shape)).astype(value.dtype)

    perturb(tree, ())
    path.write_bytes(serialization.msgpack_serialize(tree))
    return dest


@pytest.fixture(scope="module")
def runs(fixtures_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    model = load_pretrained(str(fixtures_dir / "tiny"))
    protocol = Protocol(model=str(fixtures_dir / "tiny"), tasks=("Lift",), episodes=2, max_steps=STEPS,
                        env=EnvOptions(masks=True, fast_render=True), outputs=OutputOptions(png_every=0, video=False))
    for name, p in (("base", protocol), ("same", protocol), ("longer", protocol.replace(max_steps=STEPS + 1, episodes=1))):
        execute(p, out, name, model=model, progress=False)
    return out


def test_a_run_compared_with_itself_is_identical_and_exits_0(runs, capsys):
    code = cli.main(["compare", str(runs / "base"), str(runs / "same"), "--no-frames", "--out", str(runs / "cmp_same")])
    out = capsys.readouterr().out
    assert code == 0 and "compare: IDENTICAL" in out
    result = read_back(runs / "cmp_same" / "compare.json", CompareResult)
    assert result.verdict == "IDENTICAL" and result.identical.pairs_identical == 2 and result.exit_code == 0
    assert result.drift.step0.overall.js_mean == 0 and result.drift.step0.overall.action_l2 == 0
    html = (runs / "cmp_same" / "compare.html").read_text()
    for title in ("Outcomes", "Step-0 drift", "Step-0 overlays"):
        assert title in html
    assert html.count("data:image/png;base64,") >= 4  # success chart, JS figures, both arms' overlays


def test_a_different_max_steps_exits_2_naming_the_field(runs, capsys):
    code = cli.main(["compare", str(runs / "base"), str(runs / "longer"), "--no-frames"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "max_steps" in err[0]
    assert not (runs / "longer" / "compare_base").exists()


def test_regress_with_another_model_drifts_resumes_and_fails_on_underpowered(runs, fixtures_dir, tmp_path, capsys):
    candidate = _perturbed_copy(fixtures_dir / "tiny", tmp_path / "tiny_perturbed")
    args = ["regress", "--baseline", str(runs / "base"), "--model", str(candidate), "--out", str(runs),
            "--run-name", "cand"]
    assert cli.main(args) == 0  # two failing pairs: the sequential test cannot decide, no regression shown
    out = capsys.readouterr().out
    assert "regress: UNDERPOWERED after 2 pairs" in out
    result = read_back(runs / "cand" / "regress" / "regress.json", RegressResult)
    read_back(runs / "cand" / "regress" / "compare.json", CompareResult)
    assert result.pairs_used == 2 and result.baseline_pairs == 2 and not result.sequential.decided

    compared = compare_runs(runs / "base", runs / "cand")
    assert compared.verdict != "IDENTICAL" and exit_code(compared) == 0
    step0 = compared.drift.step0.overall
    assert step0.action_l2 > 0 and step0.js_mean > 0
    assert step0.js_layer[0] == pytest.approx(0, abs=1e-6)  # layer 0 was not changed: identical step-0 attention
    assert [p.seed for p in compared.pair_details] == [0, 1]

    jsonl = (runs / "cand" / "results.jsonl").read_text()
    assert cli.main([*args, "--fail-on", "underpowered"]) == 1  # resumed: same decision, no new episode
    assert (runs / "cand" / "results.jsonl").read_text() == jsonl


def test_regress_loads_the_candidate_once_and_makes_the_first_env_once(fixtures_dir, tmp_path, monkeypatch, capsys):
    """The candidate policy the run loads is the one replayed on the baseline's recorded inputs (not loaded, and
    compiled, a second time), and the env the pre-flight check made runs the first episodes (not made again): one
    load and one env for a one-task regress. Counted on a real run, each call going through to the real one."""
    import envs
    from harness.policies import family_of

    model = str(fixtures_dir / "tiny")
    flags = ["--max-steps", "3", "--fast-render", "--no-masks", "--png-every", "0", "--no-video"]
    assert cli.main(["run", "--model", model, "--task", "Lift", "--episodes", "1", *flags, "--record-inputs",
                     "--out", str(tmp_path), "--run-name", "base"]) == 0
    calls = {"load": 0, "env": 0}
    family, load, make = family_of(model), family_of(model).load, envs.make

    def counted_load(*args, **kwargs):
        calls["load"] += 1
        return load(*args, **kwargs)

    def counted_make(*args, **kwargs):
        calls["env"] += 1
        return make(*args, **kwargs)

    monkeypatch.setattr(family, "load", counted_load)
    monkeypatch.setattr(envs, "make", counted_make)
    capsys.readouterr()
    assert cli.main(["regress", "--baseline", str(tmp_path / "base"), "--model", model, "--out", str(tmp_path),
                     "--run-name", "cand"]) == 0
    out = capsys.readouterr().out
    assert "model numerics: EQUIVALENT" in out  # the baseline's inputs were replayed, with the run's policy
    assert calls == {"load": 1, "env": 1}

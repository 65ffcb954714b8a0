"""The harness's regression gate on itself, on any x86-64 machine: every committed baseline
(results/baselines/<name>/) re-run and compared, and the gate's answers for broken candidates.

A baseline holds a small run made by scripts/make_baseline.py: manifest (with its platform), results, the first
steps' arrays and the policy's recorded inputs. What holds on every machine:
- the model's numbers: `replay` of the recorded inputs is EQUIVALENT (tests/gate/test_replay.py; under XLA capped at
  SSE4.2 through `regress`, below);
- the outcomes: the same protocol re-run passes the gate (no REGRESSED, SUSPECT or ERRORED), and compare says
  IDENTICAL exactly when the platform fingerprint is the baseline's; step 0 (same seed, same inputs when the
  renderer agrees) is EQUIVALENT or IDENTICAL.
The same-platform branch is also checked on every machine, whatever CPU it is: a baseline made here, at test time,
from the committed baseline's protocol (cut short) is IDENTICAL on rerun. A difference confined to the derived
measures (mask fractions, metrics, phases) under another measures version is named as a change of definition, while
under the same version it is a real difference.
The gate fails, with its own message, for a candidate whose every episode errors (NaN weights: ERRORED, exit 3)
and, where the model must not change (`--fail-on changed`), for one weight tensor perturbed by std 1e-3.

Cost: the reference policy is loaded once for the in-process runs of the committed protocol and the first run made
here (`reference_policy`; the second run made here loads its own, so the rerun is a fresh load); `regress` runs in a
process of its own only under other XLA flags (they are read when the process starts), else in this one.
"""

import dataclasses
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from harness.measures.attention import MEASURES_VERSION
from harness.analysis.compare import compare_runs, exit_code
from harness.cli import main as cli_main
from harness.analysis.compare_result import CompareResult
from harness.gate.results import RegressResult
from harness.run import execute
from harness.runfolder.platform import platform_fingerprint, platform_info
from harness.gate.regress import candidate_protocol
from tests.runfolder.edits import redigest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
BASELINES = REPO / "results" / "baselines"
NAMES = sorted(p.name for p in BASELINES.glob("*") if (p / "BASELINE.json").is_file())
REFERENCE = BASELINES / "reference-lift"


@pytest.fixture(scope="module")
def reference_policy():
    """The reference policy, loaded once (as `execute` loads it for the committed baseline's protocol) for the runs
    of this file that would each load it again: (model path, loaded policy)."""
    from harness.policies import load_policy
    from harness.run.protocol import policy_options

    manifest = json.loads((REFERENCE / "manifest.json").read_text())
    protocol = candidate_protocol(manifest, str(REPO / "models" / "octo-reference-robosuite"))
    return protocol.model, load_policy(protocol.model, **policy_options(protocol.text_tokenizer,
                                                                        protocol.served_conventions))


def _model(ref: str, fixtures_dir: Path) -> str:
    kind, _, rest = ref.partition(":")
    if kind == "repo":
        return str(REPO / rest)
    if kind == "fixture":
        return str(fixtures_dir / rest)
    return ref


def test_there_is_a_committed_baseline_with_recorded_inputs():
    assert NAMES, f"no baseline under {BASELINES}; make one with scripts/make_baseline.py"
    info = json.loads((REFERENCE / "BASELINE.json").read_text())
    assert info["recorded_inputs"] and len(list(REFERENCE.glob("*/*/inputs.npz"))) == 8
    manifest = json.loads((REFERENCE / "manifest.json").read_text())
    assert manifest["platform_fingerprint"].startswith("sha256:") and manifest["platform"]["gl"]["renderer"]
    size = sum(p.stat().st_size for p in REFERENCE.rglob("*") if p.is_file())
    # 6 MB: 8 episodes x 20 steps of recorded inputs, the primary camera at 128 px (8x8 patches) is most of it
    assert size < 6 * 2 ** 20, f"the committed baseline is {size / 2 ** 20:.1f} MB"


@pytest.mark.parametrize("name", NAMES)
def test_rerunning_a_committed_baseline_passes_the_gate_on_this_machine(name, fixtures_dir, tmp_path,
                                                                        reference_policy):
    """The model's fingerprint is still computed from its checkpoint files when the loaded policy is handed over
    (an Octo policy has no identity of its own), so a changed checkpoint is still named."""
    folder = BASELINES / name
    info = json.loads((folder / "BASELINE.json").read_text())
    manifest = json.loads((folder / "manifest.json").read_text())
    protocol = candidate_protocol(manifest, _model(info["model_ref"], fixtures_dir))
    shared_path, shared = reference_policy
    loaded = shared if protocol.model == shared_path else None  # another baseline's model: execute loads it
    summary = execute(protocol, tmp_path, "again", model=loaded, progress=False)
    assert summary.manifest["protocol"]["model_fingerprint"] == info["model_fingerprint"], (
        f"the model of baseline {name} changed; regenerate it (scripts/make_reference_baseline.sh for reference-lift, "
        "else octo-harness run + scripts/make_baseline.py) and commit it")

    result = compare_runs(folder, summary.run_dir)
    assert exit_code(result) == 0, (result.verdict, result.outcomes.notes)
    assert result.pairs == len(manifest["jobs"]) and not (result.missing_pairs.candidate or result.missing_pairs.baseline)
    prov = result.provenance
    same_platform = manifest.get("platform_fingerprint") == platform_fingerprint(platform_info())
    assert prov.platform["same"] == same_platform
    if same_platform:  # bit-identical trajectories are the claim here, and are checked bit for bit
        assert result.verdict == "IDENTICAL", result.identical.first_difference
    else:  # another CPU, XLA or renderer: the outcomes may move, the model's step-0 numbers may not
        assert prov.platform["differs_in"]
        assert prov.step0_numerics["verdict"] in ("IDENTICAL", "EQUIVALENT", "UNKNOWN"), prov.summary
    if prov.inputs["step0_same"]:
        assert prov.step0_numerics["verdict"] in ("IDENTICAL", "EQUIVALENT"), prov.summary


def _make_baseline_module():
    spec = importlib.util.spec_from_file_location("make_baseline", REPO / "scripts" / "make_baseline.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def made_here(tmp_path_factory, reference_policy):
    """The committed baseline's protocol cut to 2 episodes of 12 steps, run twice on this machine: a baseline made
    here from the first run (scripts/make_baseline.py), and the second run as the candidate. The first run uses the
    policy loaded for this file (after the committed protocol's rerun ran on it); the second loads the checkpoint
    again, so the rerun is a fresh load and a policy that kept state between runs would show as a difference."""
    manifest = json.loads((REFERENCE / "manifest.json").read_text())
    protocol = dataclasses.replace(candidate_protocol(manifest, str(REPO / "models" / "octo-reference-robosuite")),
                                   episodes=2, max_steps=12)
    shared_path, shared = reference_policy
    assert protocol.model == shared_path
    out = tmp_path_factory.mktemp("made-here")
    first = execute(protocol, out, "first", model=shared, progress=False)
    second = execute(protocol, out, "second", progress=False)
    baseline = _make_baseline_module().make_baseline(first.run_dir, out / "baseline", steps=8)
    return baseline, second.run_dir


def test_a_baseline_made_on_this_machine_is_identical_on_rerun(made_here):
    """The same-platform branch, on every machine: bit-identical trajectories and measures, whatever CPU CI gets."""
    baseline, candidate = made_here
    named = [p.relative_to(baseline).as_posix() for p in baseline.rglob("*.json*") if str(REPO) in p.read_text()]
    assert not named, f"a baseline names this checkout's absolute path in {named}"
    assert json.loads((baseline / "manifest.json").read_text())["model"]["source"] == "models/octo-reference-robosuite"
    result = compare_runs(baseline, candidate)
    assert result.provenance.platform["same"]
    assert result.verdict == "IDENTICAL", result.identical.first_difference
    assert result.identical.derived_measures is None and exit_code(result) == 0


def _edit_measure(run: Path, version) -> None:
    """Moves one derived measure (a mask fraction) of every episode and records `version` as the run's measures
    version, as a run written under another mask definition would hold them."""
    for npz in sorted(run.glob("*/episode_*/attention.npz")):
        with np.load(npz) as z:
            arrays = {k: z[k] for k in z.files}
        (key,) = [k for k in arrays if k.startswith("mask_fraction/image_primary/") and k.endswith("/arm")][:1]
        arrays[key] = np.where(np.isnan(arrays[key]), arrays[key], 1.0 - arrays[key]).astype(arrays[key].dtype)
        np.savez(npz, **arrays)
    redigest(run)
    manifest = json.loads((run / "manifest.json").read_text())
    manifest["measures_version"] = version
    (run / "manifest.json").write_text(json.dumps(manifest))


def test_a_changed_measure_definition_is_named_apart_from_a_real_difference(made_here, tmp_path):
    """Identical actions and attention with a mask measure that moved: under another measures version the verdict
    stays IDENTICAL and says the definition changed; under the same version it is a real difference."""
    baseline, candidate = made_here
    version = json.loads((candidate / "manifest.json").read_text())["measures_version"]
    assert version == MEASURES_VERSION
    redefined = tmp_path / "redefined"
    shutil.copytree(candidate, redefined)
    _edit_measure(redefined, version + 1)
    result = compare_runs(baseline, redefined)
    derived = result.identical.derived_measures
    assert result.verdict == "IDENTICAL" and exit_code(result) == 0
    assert derived.baseline_version == version and derived.candidate_version == version + 1
    assert derived.pairs == 2 and "mask_fraction/image_primary/" in derived.first_difference
    assert f"measures version {version} -> {version + 1}" in derived.note

    moved = tmp_path / "moved"
    shutil.copytree(candidate, moved)
    _edit_measure(moved, version)
    result = compare_runs(baseline, moved)
    assert result.verdict != "IDENTICAL" and result.identical.derived_measures is None
    assert "mask_fraction/image_primary/" in result.identical.first_difference


def _gate(argv: list[str], tmp_path: Path, env_extra: dict | None = None) -> subprocess.CompletedProcess:
    """`python -m harness.cli regress` in a process of its own: for XLA flags, which are read when a process starts."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1", **(env_extra or {})}
    return subprocess.run([sys.executable, "-m", "harness.cli", "regress", "--baseline", str(REFERENCE),
                           "--out", str(tmp_path), *argv], capture_output=True, text=True, env=env, cwd=REPO,
                          timeout=900)


def _gate_here(argv: list[str], tmp_path: Path, capsys) -> subprocess.CompletedProcess:
    """The same command in this process (`harness.cli.main`, the function `python -m harness.cli` exits with): its
    exit code and what it printed, without a second interpreter start (imports, JAX and GL set up again)."""
    capsys.readouterr()
    code = cli_main(["regress", "--baseline", str(REFERENCE), "--out", str(tmp_path), *argv])
    printed = capsys.readouterr()
    return subprocess.CompletedProcess(["octo-harness", "regress", *argv], code, printed.out, printed.err)


@pytest.mark.slow
def test_the_gate_passes_the_unchanged_model_under_another_machines_numerics(tmp_path):
    """XLA capped at SSE4.2: other bits from step 0 on, maybe other trajectories; the gate still passes, says the
    model's numbers are EQUIVALENT and that the platforms differ."""
    proc = _gate(["--model", "models/octo-reference-robosuite", "--fail-on", "changed"], tmp_path,
                 {"XLA_FLAGS": "--xla_cpu_max_isa=SSE4_2"})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (regress_json,) = tmp_path.glob("*/regress/regress.json")
    result = RegressResult.from_json(json.loads(regress_json.read_text()))
    assert result.replay.verdict == "EQUIVALENT"
    # other bits, within tolerance (this was also tests/gate/test_replay.py's own `replay` under SSE4.2: one
    # compilation of the model under these flags now serves both)
    assert 0 < result.replay.action_change_max <= result.replay.tolerances.action
    compare = CompareResult.from_json(json.loads((regress_json.parent / "compare.json").read_text()))
    assert "xla_flags" in compare.provenance.platform["differs_in"]
    assert "model numerics: EQUIVALENT" in proc.stdout and "platform: different" in proc.stdout


def _broken_model(dest: Path, change) -> Path:
    from flax import serialization

    shutil.copytree(REPO / "models" / "octo-reference-robosuite", dest)
    (path,) = dest.glob("*/default/checkpoint")
    tree = serialization.msgpack_restore(path.read_bytes())
    node = tree["octo_transformer"]["BlockTransformer_0"]["Transformer_0"]["encoderblock_1"]["MlpBlock_0"]["Dense_1"]
    node["kernel"] = change(np.asarray(node["kernel"])).astype(np.float32)
    path.write_bytes(serialization.msgpack_serialize(tree))
    return dest


def test_the_gate_fails_a_candidate_whose_every_episode_errors(tmp_path, capsys):
    """NaN weights: every action is NaN, every episode errors (the rollout refuses non-finite actions): ERRORED, exit 3."""
    model = _broken_model(tmp_path / "nan", lambda k: np.full_like(k, np.nan))
    proc = _gate_here(["--model", str(model)], tmp_path / "runs", capsys)
    assert proc.returncode == 3, proc.stdout + proc.stderr
    assert "ERRORED" in proc.stdout
    rows = [json.loads(line) for line in next((tmp_path / "runs").glob("*/results.jsonl")).read_text().splitlines()]
    assert rows and all(r["status"] == "failed" and "not finite" in r["error"] for r in rows)


def test_the_gate_fails_a_candidate_with_one_weight_tensor_perturbed_where_the_model_must_not_change(tmp_path, capsys):
    """One episode of the candidate (it was 2) still tests it: what is asserted is the model-numerics verdict, and
    `replay` compares the candidate on every recorded input of the baseline (its 8 episodes) whatever
    --max-episodes; the candidate's own episodes only feed the outcome comparison, which at 1 or 2 pairs cannot
    reach REGRESSED (an exact McNemar test needs at least 6 pairs)."""
    rng = np.random.default_rng(0)
    model = _broken_model(tmp_path / "perturbed", lambda k: k + 1e-3 * rng.standard_normal(k.shape))
    proc = _gate_here(["--model", str(model), "--fail-on", "changed", "--max-episodes", "1"], tmp_path / "runs",
                      capsys)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "model numerics: CHANGED" in proc.stdout and "step 0" in proc.stdout

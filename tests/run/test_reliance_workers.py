"""Region reliance with any executor (issue 45): two env-worker processes give the sequential run's reliance.jsonl,
bit for bit (the masks travel with the request; the probe runs in the policy's process with the step's own rng).
A run with the probe compares IDENTICAL with one without and names the measure only one took; resume refuses to turn
the probe on halfway (issue 72)."""

from __future__ import annotations

import dataclasses
import json

import pytest

import envs
from harness.policies import as_policy
from harness.outputs.writers import OutputOptions
from harness.policy import PolicyConfig
from harness.run import execute
from harness.run.protocol import Protocol
from harness.run.workers import WorkersExecutor

CAMERAS = (("image_primary", "agentview", 64), ("image_wrist", "robot0_eye_in_hand", 32))  # the tiny model's sizes


def _rows(summary) -> list[list[dict]]:
    """Each episode's reliance rows without the run's name."""
    out = []
    for row in summary.rows:
        lines = (summary.episode_dir(row) / "reliance.jsonl").read_text().splitlines()
        out.append([{k: v for k, v in json.loads(line).items() if k != "run"} for line in lines])
    return out


@pytest.fixture(scope="module")
def runs(fixtures_dir, tmp_path_factory):
    """The tiny fixture on 2 Lift episodes of 3 steps: with reliance every 2nd step, sequentially and on two workers,
    and the same protocol without reliance."""
    from harness.octo import load_pretrained

    model = load_pretrained(str(fixtures_dir / "tiny"))
    protocol = Protocol(model=model.source, tasks=("Lift",), episodes=2, seed=5, max_steps=3,
                        env=envs.EnvOptions(masks=True, fast_render=True, cameras=CAMERAS),
                        policy=PolicyConfig(reliance_every=2), outputs=OutputOptions(png_every=0, video=False))
    out = tmp_path_factory.mktemp("reliance")
    sequential = execute(protocol, out, "seq", model=model, progress=False)
    parallel = execute(protocol, out, "two", model=model, progress=False,
                       executor=lambda context, m: WorkersExecutor(context, as_policy(m), workers=2))
    plain = execute(dataclasses.replace(protocol, policy=PolicyConfig()), out, "plain", model=model, progress=False)
    return {"model": model, "protocol": protocol, "out": out, "seq": sequential, "two": parallel, "plain": plain}


@pytest.mark.slow
def test_two_workers_give_the_sequential_reliance_bit_for_bit(runs):
    sequential, parallel = runs["seq"], runs["two"]
    assert [r.status for r in parallel.rows] == ["ok", "ok"]
    a, b = _rows(sequential), _rows(parallel)
    assert a == b  # every change, share and area: the same floats, not close ones
    assert {r["step"] for r in a[0]} == {0, 2} and {r["episode"] for e in a for r in e} == {0, 1}


@pytest.mark.slow
def test_a_run_with_a_probe_compares_identical_with_one_without_and_names_the_measure(runs):
    """Issue 72: the probe's options are derived as neutral from the registry (it declares it never changes actions),
    so the two runs pair, are IDENTICAL (actions and attention bit for bit), and one line names what only one took."""
    from harness.analysis.compare import compare_runs, exit_code

    result = compare_runs(runs["seq"].run_dir, runs["plain"].run_dir)
    assert result.verdict == "IDENTICAL" and exit_code(result, "changed") == 0, result.identical.first_difference
    assert result.one_side_measures.baseline == ("reliance",) and result.one_side_measures.candidate == ()
    lines = [n for n in result.outcomes.notes if n.startswith("measures only one run took")]
    assert lines == ["measures only one run took: reliance only in the baseline (measured beside the actions; "
                     "compared where both runs have them)"]
    assert not result.differs.other and "reliance" not in result.provenance.summary
    swapped = compare_runs(runs["plain"].run_dir, runs["seq"].run_dir)
    assert swapped.verdict == "IDENTICAL" and swapped.one_side_measures.candidate == ("reliance",)
    same = compare_runs(runs["seq"].run_dir, runs["two"].run_dir)
    assert same.verdict == "IDENTICAL" and "one_side_measures" not in same.to_json()


@pytest.mark.slow
def test_resume_refuses_a_probe_option_that_would_measure_some_episodes_only(runs):
    """Resuming the plain run under its name with reliance on would leave its episodes measured unevenly: refused in
    one line naming the option, nothing written."""
    from harness.run.driver import ProtocolMismatchError

    before = sorted(p.name for p in runs["plain"].run_dir.rglob("*"))
    with pytest.raises(ProtocolMismatchError) as raised:
        execute(runs["protocol"], runs["out"], "plain", model=runs["model"], progress=False)
    message = str(raised.value)
    assert "\n" not in message and "policy.reliance_every" in message, message
    assert sorted(p.name for p in runs["plain"].run_dir.rglob("*")) == before


@pytest.mark.slow
def test_regress_inherits_the_baselines_probes_and_drops_them_when_told(runs):
    """`regress` runs the baseline's protocol: its probes too, unless --drop-probes (then only the probes' fields
    return to their defaults: the policy's own options stay the baseline's)."""
    from harness.gate.regress import candidate_protocol

    manifest = json.loads((runs["seq"].run_dir / "manifest.json").read_text())
    inherited = candidate_protocol(manifest, runs["model"].source)
    assert inherited.policy.reliance_every == 2 and inherited.policy.reliance_fill == "impute"
    dropped = candidate_protocol(manifest, runs["model"].source, drop_probes=True)
    assert dropped.policy == PolicyConfig() and dropped.env == inherited.env and dropped.tasks == inherited.tasks
    assert "reliance_every" not in dropped.policy.to_dict()

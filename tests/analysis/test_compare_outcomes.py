"""compare's outcome statistics on run folders written by hand (no arrays): pairing, Holm, verdicts, exit codes."""

import json

import pytest

from harness import cli
from harness.analysis.compare import compare_runs, exit_code, incompatible_fields
from harness.analysis.compare_result import MissingPairs
from harness.analysis.paired import PairedCounts, holm_adjust, mcnemar_exact
from harness.verdicts import GateVerdict
from harness.runfolder.schema import protocol_hash

PROTOCOL = {"model": "m", "model_fingerprint": "x", "tasks": ["Lift", "Stack"], "episodes": 10, "seed": 0,
            "max_steps": 50, "execution": "temporal_ensemble:0", "instruction": None, "goal_images": None,
            "goal_fingerprint": None, "env": {"masks": True, "fast_render": True, "cameras": None,
                                              "image_convention": "upright", "action_space": "octo-delta"},
            "policy": {"execution": "temporal_ensemble", "receding_steps": 1, "ensemble_weight": 0.0,
                       "dataset_key": None, "full_attention": False},
            "outputs": {"png_every": 1}, "harness_version": "1"}


def write_run(folder, successes: dict[str, list[bool | None]], protocol=None, model="m"):
    """A run folder by hand: {task: [success per episode]} with None for an episode that errored (status
    "failed", no outcome); the protocol's tasks and episode count follow `successes` (as the run store's do)."""
    episodes = max(len(flags) for flags in successes.values())
    protocol = {**(protocol or PROTOCOL), "model": model, "tasks": list(successes), "episodes": episodes}
    jobs = [[task, k, k] for task in successes for k in range(episodes)]
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text(json.dumps({
        "format": "octo-harness-run/1", "run": folder.name, "protocol": protocol, "jobs": jobs,
        "protocol_hash": protocol_hash(protocol),
        "model": {"source": model, "is_random": False}}))
    rows = [{"run": folder.name, "task": task, "episode": k, "seed": k, "status": "ok" if flag is not None else "failed",
             "success": flag, "steps": 5, "directory": f"{task}/episode_{k}"}
            for task, flags in successes.items() for k, flag in enumerate(flags)]
    (folder / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return folder


def test_a_significant_drop_is_regressed_with_holm_across_tasks_and_exits_1(tmp_path, capsys):
    base = write_run(tmp_path / "base", {"Lift": [True] * 10, "Stack": [True, False] * 5})
    cand = write_run(tmp_path / "cand", {"Lift": [False] * 10, "Stack": [True, False] * 5}, model="m2")
    result = compare_runs(base, cand)
    lift, stack, pooled = result.outcomes.tasks["Lift"], result.outcomes.tasks["Stack"], result.outcomes.overall
    assert lift.table == PairedCounts(both=0, baseline_only=10, candidate_only=0, neither=0)
    assert lift.mcnemar_p == pytest.approx(2 / 1024)
    # family = Lift, Stack, pooled: Holm multiplies the smallest p by 3
    expected = holm_adjust([2 / 1024, 1.0, mcnemar_exact(10, 0)])
    assert [lift.mcnemar_p_holm, stack.mcnemar_p_holm, pooled.mcnemar_p_holm] == pytest.approx(expected)
    assert lift.verdict == GateVerdict.REGRESSED and stack.verdict == GateVerdict.UNDERPOWERED and pooled.verdict == GateVerdict.REGRESSED
    assert stack.more_pairs_needed > 0
    assert result.verdict == GateVerdict.REGRESSED and exit_code(result) == 1
    assert cli.main(["compare", str(base), str(cand), "--no-frames"]) == 1
    out = capsys.readouterr().out
    assert "compare: REGRESSED" in out and "| Lift | 10 |" in out
    assert (cand / "compare_base" / "compare.html").is_file()


def test_missing_pairs_are_reported_and_make_the_candidate_incomplete(tmp_path):
    """A candidate lacking the baseline's episodes cannot pass (issue 28: it used to be UNDERPOWERED, exit 0)."""
    base = write_run(tmp_path / "base", {"Lift": [True, False, True, True]})
    cand = write_run(tmp_path / "cand", {"Lift": [True, False]}, model="m2")  # still running: 2 of 4 episodes
    result = compare_runs(base, cand)
    assert result.pairs == 2 and result.missing_pairs == MissingPairs(candidate=(("Lift", 2), ("Lift", 3)), baseline=())
    assert result.verdict == GateVerdict.INCOMPLETE and result.outcomes.overall.verdict == GateVerdict.UNDERPOWERED
    assert {exit_code(result, fail_on) for fail_on in ("regressed", "suspect", "underpowered", "changed")} == {4}
    lenient = compare_runs(base, cand, require_complete=False)  # regress's view: the pairs that ran
    assert lenient.verdict == GateVerdict.UNDERPOWERED and exit_code(lenient) == 0 and exit_code(lenient, "underpowered") == 1


def test_only_outcome_changing_protocol_fields_are_incompatible():
    other = json.loads(json.dumps(PROTOCOL))
    other.update(model="m2", model_fingerprint="y", episodes=50, harness_version="2", outputs={"png_every": 0})
    other["policy"]["dataset_key"] = "robomimic"
    assert incompatible_fields(PROTOCOL, other) == []
    other["env"]["action_space"] = "robosuite"
    other["env"]["cameras"] = {"image_primary": ["agentview", 84]}
    other["policy"]["receding_steps"] = 4
    assert incompatible_fields(PROTOCOL, other) == ["env.action_space", "env.cameras", "policy.receding_steps"]


def test_not_a_run_is_one_line_exit_2(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code = cli.main(["compare", str(tmp_path / "empty"), str(tmp_path / "empty")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "run folder" in err[0]


def test_regress_feeds_complete_rounds_in_order_to_each_tasks_own_test():
    import numpy as np

    from harness.analysis.sequential import SequentialConfig
    from harness.run.protocol import EpisodeJob
    from harness.gate.regress import round_order, sequential_state

    tasks = ("Lift", "Stack")
    jobs = [EpisodeJob(t, k, 10 + k) for t in tasks for k in range(3)]  # task-major, as a protocol lists them
    assert [(j.task, j.episode) for j in round_order(jobs, tasks)] == [
        ("Lift", 0), ("Stack", 0), ("Lift", 1), ("Stack", 1), ("Lift", 2), ("Stack", 2)]
    baseline = {(t, 10 + k): True for t in tasks for k in range(3)}
    candidate = {("Lift", 10): False, ("Stack", 10): True, ("Lift", 11): False, ("Stack", 11): None,
                 ("Lift", 12): False}  # Stack's second candidate episode errored; round 2 is not finished
    config = SequentialConfig(alpha=0.05, max_drop=0.1)
    test = sequential_state(baseline, candidate, jobs, tasks, config)
    assert test.rounds == 2 and test.task_alpha == pytest.approx(0.025)
    lift, stack = test.tests["Lift"], test.tests["Stack"]
    assert lift.units == 2 and stack.units == 1 and test.errored == {"Lift": 0, "Stack": 1}
    assert lift.config.alpha == pytest.approx(0.025) and lift.config.threshold == pytest.approx(80.0)
    bets = lift.config.bets("regression")
    assert lift.wealth("regression") == pytest.approx(np.mean((1 + bets) ** 2))  # units -1, -1
    assert stack.wealth("regression") == pytest.approx(1.0)  # one concordant pair: no evidence either way

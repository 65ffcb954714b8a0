"""The report's Faithfulness section: summaries, sentences and the intervention table on hand-made runs."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from harness.report import faithfulness as R


def _row(episode, step, method, deletion, control, camera="image_primary"):
    return {"task": "Lift", "episode": episode, "step": step, "camera": camera, "method": method, "change_all": 0.5,
            "deletion_auc": deletion, "random_deletion_auc": control, "insertion_auc": 1 - deletion,
            "random_insertion_auc": 1 - control, "top_k/2": deletion, "random_k/2": control}


def test_summary_ratios_intervals_and_sentence():
    rows = [_row(e, s, "attention:2", 0.6 + 0.01 * e, 0.3) for e in range(6) for s in range(3)]
    rows += [_row(e, s, "random", 0.3 + 0.01 * (s - 1), 0.3) for e in range(6) for s in range(3)]
    rows += [_row(e, s, "saliency", np.nan, np.nan, camera="image_wrist") for e in range(2) for s in range(2)]
    table = R.summarise(rows, "run")
    by = {(r[2], r[3]): r for r in table}
    attn = by[("image_primary", "attention:2")]
    assert attn[4] == 18 and attn[5] == 6
    assert attn[7] == pytest.approx(np.mean([0.6 + 0.01 * e for e in range(6)]) / 0.3)
    assert attn[8] > 1 and attn[9] > attn[7] > attn[8]
    assert by[("image_primary", "random")][7] == pytest.approx(1.0)
    assert by[("image_primary", "attention:2")][13] == pytest.approx(attn[7]) and attn[14] == 2
    assert np.isnan(by[("image_wrist", "saliency")][7]) and by[("image_wrist", "saliency")][4] == 0
    text = R.sentence("Lift", table)
    assert text.startswith("Lift, image_primary: layer 2 attention ranks the patches the action depends on better than random")
    assert "(18 steps, 6 episodes)" in text
    assert R.heatmap("Lift", table)[:8] == b"\x89PNG\r\n\x1a\n"


def _record(name, policy, outcomes, tmp: Path):
    episodes = tuple(SimpleNamespace(task="Lift", episode=i, seed=i, ok=True, success=s, directory=tmp / name / str(i))
                     for i, s in enumerate(outcomes))
    manifest = {"protocol": {"model_fingerprint": "sha256:x", "max_steps": 50, "env": {"fast_render": True},
                             "policy": {"execution": "temporal_ensemble", **policy}}}
    return SimpleNamespace(name=name, tasks=("Lift",), episodes=episodes, manifest=manifest)


def test_intervention_rows_pair_by_seed_with_the_plain_run(tmp_path):
    plain = _record("plain", {}, [True] * 9 + [False], tmp_path)
    masked = _record("masked", {"intervention": "mask-all"}, [False] * 8 + [True, False], tmp_path)
    other = _record("other", {"intervention": "mask-random:2", "sampler": "v0.1.0"}, [True] * 10, tmp_path)  # no plain arm
    rows = R.intervention_rows([plain, masked, other])
    assert len(rows) == 1
    row = dict(zip(R.INTERVENTION_COLUMNS, rows[0]))
    assert row["intervention"] == "mask-all" and row["pairs"] == 10
    assert row["baseline_successes"] == 9 and row["successes"] == 1 and row["difference"] == pytest.approx(-0.8)
    assert row["difference_ci_high"] < 0 < row["baseline_rate"]
    assert row["mcnemar_p"] == pytest.approx(2 / 2 ** 8)  # 8 discordant pairs, all baseline-only: 2 * 0.5^8
    assert "mask-all" in R.markdown([plain, masked])


def test_mask_top_is_also_paired_with_mask_random_of_the_same_k(tmp_path):
    plain = _record("plain", {}, [True] * 10, tmp_path)
    top = _record("top", {"intervention": "mask-top:2:saliency"}, [False] * 5 + [True] * 5, tmp_path)
    rand = _record("rand", {"intervention": "mask-random:2"}, [True] * 9 + [False], tmp_path)
    other_k = _record("rand3", {"intervention": "mask-random:3"}, [False] * 10, tmp_path)
    rows = [dict(zip(R.INTERVENTION_COLUMNS, r)) for r in R.intervention_rows([plain, top, rand, other_k])]
    pairs = {(r["run"], r["baseline_run"]) for r in rows}
    assert pairs == {("top", "plain"), ("top", "rand"), ("rand", "plain"), ("rand3", "plain")}
    versus_random = next(r for r in rows if r["baseline_run"] == "rand")
    assert versus_random["difference"] == pytest.approx(-0.4) and versus_random["baseline_successes"] == 9


def test_an_intervention_run_on_several_tasks_gets_a_pooled_row(tmp_path):
    def on(task, record):
        record.tasks = (task,)
        record.episodes = tuple(SimpleNamespace(**{**vars(e), "task": task}) for e in record.episodes)
        return record

    lift_plain = on("Lift", _record("lp", {}, [True] * 10, tmp_path))
    lift_top = on("Lift", _record("lt", {"intervention": "mask-all"}, [False] * 10, tmp_path))
    stack_plain = on("Stack", _record("sp", {}, [True] * 5 + [False] * 5, tmp_path))
    stack_top = on("Stack", _record("st", {"intervention": "mask-all"}, [False] * 10, tmp_path))
    rows = [dict(zip(R.INTERVENTION_COLUMNS, r)) for r in R.intervention_rows([lift_plain, lift_top, stack_plain, stack_top])]
    pooled = next(r for r in rows if r["task"] == "pooled")
    assert pooled["pairs"] == 20 and pooled["baseline_successes"] == 15 and pooled["successes"] == 0
    assert pooled["run"] == "lt+st" and pooled["baseline_run"] == "lp+sp"
    assert pooled["mcnemar_p"] == pytest.approx(2 * 0.5 ** 15)
    assert len(rows) == 3

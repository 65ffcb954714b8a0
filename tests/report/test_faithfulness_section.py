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
    d, dlo, dhi = attn[7:10]
    assert text == f"Lift, image_primary: layer 2 attention ranks best, better than random (deletion AUC {d:.2f}x random " \
                   f"[{dlo:.2f}, {dhi:.2f}], 6 episodes)."
    assert len(text.split()) <= 25
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


def _curve_row(episode, method, curve, fill="mean", camera="image_wrist", lerf=None):
    fractions = [i / 4 for i in range(5)]
    auc = float(np.trapz(curve, fractions))
    return {"task": "Lift", "episode": episode, "step": 0, "camera": camera, "method": method, "fill": fill,
            "change_all": curve[-1], "deletion_auc": auc, "random_deletion_auc": 0.5, "insertion_auc": 0.5,
            "random_insertion_auc": 0.5, "lerf_auc": lerf if lerf is not None else auc, "random_lerf_auc": 0.5,
            "fractions": fractions, "deletion_curve": curve, "top_k/1": curve[1], "random_k/1": 0.25}


def test_lerf_fill_and_where_an_ordering_first_beats_random():
    random_curve = [0.0, 0.25, 0.5, 0.75, 1.0]
    early = [0.0, 0.5, 0.8, 0.9, 1.0]  # above random (x1.1) from k/n = 0.25 on
    late = [0.0, 0.2, 0.6, 0.9, 1.0]  # above only from 0.5 on
    never = [0.0, 0.1, 0.2, 0.3, 1.0]  # below random until the whole camera goes
    rows = [_curve_row(e, m, c, lerf=0.25 if m == "early" else None) for e in range(3)
            for m, c in (("random", random_curve), ("attention:0", early), ("attention:1", late), ("saliency", never))]
    table = {r[3]: dict(zip(R.FAITH_COLUMNS, r)) for r in R.summarise(rows, "run")}
    assert table["attention:0"]["beats_random_from"] == 0.25
    assert table["attention:1"]["beats_random_from"] == 0.5
    assert np.isnan(table["saliency"]["beats_random_from"])
    assert table["saliency"]["fill"] == "mean"
    assert table["saliency"]["lerf_rel"] == pytest.approx(np.trapz(never, [0, .25, .5, .75, 1]) / 0.5)


def test_fill_ranking_reports_how_the_order_of_methods_changes():
    rows = []
    for fill, values in (("mean", {"attention:0": 0.6, "rollout": 0.8, "saliency": 0.7}),
                         ("impute", {"attention:0": 1.3, "rollout": 0.9, "saliency": 1.1})):
        for m, v in values.items():
            rows += [{**_curve_row(e, m, [0, .25, .5, .75, 1.0], fill=fill), "deletion_auc": v * 0.5} for e in range(3)]
    faith = R.summarise([r for r in rows if r["fill"] == "mean"], "mean") + \
        R.summarise([r for r in rows if r["fill"] == "impute"], "impute")
    ranking = R.fill_ranking(faith)
    by = {r[2]: r[3] for r in ranking}
    assert list(by["rollout"]) == ["mean", "impute"]  # mean first
    assert by["rollout"]["mean"][1] == 1 and by["rollout"]["impute"][1] == 3
    assert by["attention:0"]["mean"][1] == 3 and by["attention:0"]["impute"][1] == 1
    assert by["spearman vs mean"]["impute"][0] == pytest.approx(-1.0)
    assert R.fill_ranking(R.summarise([r for r in rows if r["fill"] == "mean"], "mean")) == []  # one fill: nothing


def test_camera_rows_flag_open_and_closed_loop_disagreement(tmp_path):
    """The wrist camera: masking it stops the policy, masking its top-4 by attention:2 costs more than 4 random
    patches, yet open loop every ranking is below random: flagged. The primary camera agrees."""
    def run(name, policy, outcomes, faith_rows=()):
        record = _record(name, policy, outcomes, tmp_path)
        for e in record.episodes:
            e.directory.mkdir(parents=True, exist_ok=True)
            (e.directory / "faithfulness.jsonl").write_text("".join(json.dumps(r) + "\n" for r in faith_rows
                                                                    if r["episode"] == e.episode))
        return record

    below = [0.0, 0.1, 0.2, 0.3, 1.0]
    above = [0.0, 0.6, 0.8, 0.9, 1.0]
    faith = [_curve_row(e, "attention:2", below, camera="image_wrist") for e in range(6)]
    faith += [{**_curve_row(e, "attention:2", below, camera="image_wrist"), "deletion_auc": 0.3 + 0.01 * e} for e in range(6, 12)]
    faith += [{**_curve_row(e, "attention:2", above, camera="image_primary"), "deletion_auc": 0.7 + 0.01 * e} for e in range(12)]
    faith += [_curve_row(e, "random", [0, .25, .5, .75, 1.0], camera=c) for e in range(12) for c in ("image_wrist", "image_primary")]
    open_run = run("open", {"faithfulness_every": 10}, [True] * 12, faith)
    plain = run("plain", {}, [True] * 12)
    all_wrist = run("all-wrist", {"intervention": "mask-all@image_wrist"}, [False] * 12)
    top = run("top-wrist", {"intervention": "mask-top:4:attention:2@image_wrist"}, [False] * 10 + [True] * 2)
    rand = run("random-wrist", {"intervention": "mask-random:4@image_wrist"}, [True] * 12)
    runs = [open_run, plain, all_wrist, top, rand]
    cams = [dict(zip(R.CAMERA_COLUMNS, c)) for c in R.camera_rows(runs)]
    wrist = [c for c in cams if c["camera"] == "image_wrist"]
    assert len(wrist) == 1 and wrist[0]["method"] == "attention:2"
    assert wrist[0]["mask_all"] == "12/12 -> 0/12" and wrist[0]["mask_all_p"] < 0.001
    assert wrist[0]["top_vs_random_difference"] == pytest.approx(-10 / 12)
    assert wrist[0]["agreement"] == "DISAGREE"  # closed loop: better than random; open loop: worse
    assert wrist[0]["open_ci_high"] < 1
    assert all(c["camera"] != "image_primary" for c in cams)  # no closed-loop arm of its own: not in the table
    text = R.camera_sentence("Lift", "image_wrist", R.open_rows(runs), R.camera_rows(runs))
    p = wrist[0]["mask_all_p"]
    assert text == f"Lift, image_wrist: open and closed loop DISAGREE. Masking the camera: 12/12 -> 0/12 (difference " \
                   f"-1.00, p = {p:.3g})." and len(text.split()) <= 25
    ((*_, methods, ratios, below, above, first, start),) = R.camera_fill_rows("Lift", "image_wrist", R.open_rows(runs))
    assert (methods, below, above, first, start) == ("1", "1", "0", "none up to half the camera", "-")
    assert ratios == f"{wrist[0]['open_loop_deletion']:.2f}-{wrist[0]['open_loop_deletion']:.2f}"
    md = R.markdown(runs)
    assert f"| Lift | image_wrist | mean | 1 | {ratios} | 1 | 0 | none up to half the camera | - |" in md
    assert "| Lift | image_wrist | mean | attention:2 |" in md and "open vs closed loop" in md
    assert "faithfulness_cameras.csv" in R.tables(runs)


def test_camera_rows_without_closed_loop_or_open_loop_are_empty_or_na(tmp_path):
    plain = _record("plain", {}, [True] * 4, tmp_path)
    masked = _record("m", {"intervention": "mask-all@image_wrist"}, [False] * 4, tmp_path)
    assert R.camera_rows([plain]) == []
    (row,) = R.camera_rows([plain, masked])  # a mask-all arm without any open-loop run: open loop n/a
    assert row[13] == "n/a" and row[7] == "4/4 -> 0/4"

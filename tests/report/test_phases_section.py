"""End to end: a real run of the committed reference policy with phases, masks and attention controls -> files ->
`octo-harness report` -> Phases and Position sections rendered in headless Chromium, every number from a CSV next
to the page; foreign or damaged files are left out, not trusted."""

import csv
import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from harness import cli
from harness.analysis import position as Q
from harness.measures.attention import camera_maps
from harness.octo.tokens import TokenMap
from tests.runfolder.edits import redigest, strip_masks  # as if a run had written the edited files
from tests.helpers import browser as _browser

MODEL = Path(__file__).resolve().parents[2] / "models" / "octo-reference-robosuite"
EVERY = 3


def _rows(path: Path) -> list[dict]:
    return list(csv.DictReader(io.StringIO(path.read_text())))


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs")
    code = cli.main(["run", "--model", str(MODEL), "--task", "Lift", "--episodes", "2", "--seed", "1", "--max-steps", "40",
                     "--attention-controls", "blank,mirror", "--controls-every", str(EVERY), "--record-inputs",
                     "--png-every", "0", "--no-video", "--fast-render", "--out", str(out), "--run-name", "phases"])
    assert code == 0
    return out / "phases"


@pytest.fixture(scope="module")
def report(run) -> Path:
    assert cli.main(["report", str(run), "--out", str(run.parent / "report"), "--resamples", "200"]) == 0
    return run.parent / "report"


@pytest.mark.slow
def test_run_records_phases_and_controls(run):
    manifest = json.loads((run / "manifest.json").read_text())
    policy = manifest["protocol"]["policy"]
    assert policy["attention_controls"] == "blank,mirror" and policy["controls_every"] == EVERY
    for directory in sorted(run.glob("Lift/episode_*")):
        summary = json.loads((directory / "episode.json").read_text())
        metrics = [json.loads(line) for line in (directory / "metrics.jsonl").read_text().splitlines()]
        phases = summary["phases"]
        assert phases["names"] == ["approach", "grasp", "lift"] and phases["steps"]["approach"] >= 1
        assert sum(phases["steps"].values()) == summary["steps"] == len(metrics)
        with np.load(directory / "attention.npz") as z:
            names = list(z["phase_names"])
            assert [names[i] for i in z["phase"]] == [m["phase"] for m in metrics]
            assert {"mask_fraction/image_primary/gripper", "mask_fraction/image_primary/arm"} <= set(z.files)
            attention = z["readout_attention"]
        with np.load(directory / "controls.npz") as c:
            assert list(c["step"]) == list(range(0, summary["steps"], EVERY))
            assert c["blank"].shape == c["mirror"].shape == (len(c["step"]), *attention.shape[1:])
            assert c["blank"].dtype == np.float16
            assert not np.array_equal(c["blank"], attention[c["step"]])
        if summary["success"]:
            assert phases["furthest"] == "lift"  # the final state, after the last recorded step, counts


@pytest.mark.slow
def test_position_bound_csv_has_the_issue_columns_and_agrees_with_the_arrays(run, report):
    rows = _rows(report / "tables" / "position_bound.csv")
    assert list(rows[0]) == ["run", "task", "camera", "layer", "head", "row", "col", "real", "blank", "mirrored",
                             "flagged"]
    cameras = {r["camera"] for r in rows}
    assert cameras == {"image_primary", "image_wrist"}
    assert len(rows) == 4 * 5 * (64 + 16)  # layers x (heads + mean) x patches of both cameras
    # recompute the head mean of layer 1 on the primary camera from the episode files
    real, blank, mirror = [], [], []
    for directory in sorted(run.glob("Lift/episode_*")):
        with np.load(directory / "attention.npz") as z, np.load(directory / "controls.npz") as c:
            tokens = TokenMap.from_arrays({k: z[k] for k in z.files if k.startswith("tokens/")})
            for out, x in ((real, z["readout_attention"][c["step"]]), (blank, c["blank"]), (mirror, c["mirror"])):
                out.append(camera_maps(x.astype(np.float32), tokens, "image_primary").mean(axis=3))
    means = Q.patch_means(np.concatenate(real), np.concatenate(blank), np.concatenate(mirror))
    flags = Q.flag_position_bound(means.real, means.blank, means.mirrored)
    for r in rows:
        if r["camera"] == "image_primary" and r["layer"] == "1" and r["head"] == "mean":
            i, j = int(r["row"]), int(r["col"])
            assert float(r["real"]) == pytest.approx(means.real[1, -1, i, j], rel=1e-5)
            assert float(r["blank"]) == pytest.approx(means.blank[1, -1, i, j], rel=1e-5)
            assert float(r["mirrored"]) == pytest.approx(means.mirrored[1, -1, i, j], rel=1e-5)
            assert (r["flagged"] == "True") == bool(flags[1, -1, i, j])
    shares = _rows(report / "tables" / "position_share.csv")
    assert all(0.0 <= float(s["remaining_share"]) <= 1.0 for s in shares)
    lifts = _rows(report / "tables" / "position_lift.csv")
    assert {r["mask"] for r in lifts} == {"target", "gripper"}  # Lift has no goal region


def test_phase_tables_agree_with_the_episodes(run, report):
    steps = _rows(report / "tables" / "phase_steps.csv")
    summaries = [json.loads(p.read_text()) for p in sorted(run.glob("Lift/episode_*/episode.json"))]
    for r in steps:
        assert int(r["episodes"]) == 2
        expected = np.mean([s["phases"]["steps"][r["phase"]] for s in summaries])
        assert float(r["steps_mean"]) == pytest.approx(expected)
    table = _rows(report / "tables" / "phase_table.csv")
    assert {r["mask"] for r in table} >= {"target", "gripper", "background"}
    assert {r["event"] for r in _rows(report / "tables" / "phase_events.csv")} >= {"grasp onset"}
    assert list(_rows(report / "tables" / "phase_tests.csv")[0])[5:8] == ["test", "statistic", "p"]


def test_eval_md_gets_the_phases_and_position_section_from_its_figures_file(run, tmp_path):
    """`python -m harness.report.phases RUN --eval-md EVAL.md` (scripts/phases_reference.sh): the phase tables and
    the position tables in one section, rendered from figures/phases-and-position.json; `.position` alone too."""
    from harness.report import figures_file, phases, position

    eval_md = tmp_path / "EVAL.md"
    eval_md.write_text("# model\n\n## Robustness\n\nkept\n")
    assert phases.main([str(run), "--eval-md", str(eval_md)]) == 0
    text = eval_md.read_text()
    doc = figures_file.read(tmp_path / "figures" / "phases-and-position.json")
    assert "## Robustness\n\nkept\n" in text and text.endswith(figures_file.render(doc))
    assert "### Phases" in text and "### Position" in text and "| phase | episodes reaching it |" in text
    assert position.main([str(run), "--eval-md", str(eval_md)]) == 0
    assert (tmp_path / "figures" / "position.json").is_file() and eval_md.read_text().count("\n## Position\n") == 1


def test_sections_render_in_headless_chromium(report, tmp_path):
    dom = _browser(report / "report.html", tmp_path, "--dump-dom", "--virtual-time-budget=10000").stdout
    for title in ("Phases", "Position", "Lift: phases"):
        assert f">{title}</h" in dom, title
    assert 'href="#phases"' in dom and 'href="#position"' in dom
    total = re.search(r'data-images-total="(\d+)"', dom)
    ok = re.search(r'data-images-ok="(\d+)"', dom)
    assert total and ok and int(ok.group(1)) == int(total.group(1))
    assert (report / "plots" / "position_lift_phases.png").is_file()
    assert (report / "plots" / "phase_events_lift_phases.png").is_file()


def test_foreign_and_damaged_files_are_left_out(run, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    first, second = sorted(copy.glob("Lift/episode_*"))
    (first / "controls.npz").write_bytes(b"PK\x03\x04 not a zip")  # damaged
    with np.load(second / "attention.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["phase"] = np.full_like(arrays["phase"], 7)  # indices beyond phase_names: not what a writer stores
    np.savez(second / "attention.npz", **arrays)
    with np.load(second / "controls.npz") as c:
        controls = {k: c[k] for k in c.files}
    controls["step"] = controls["step"] + 1000  # steps the episode never recorded
    np.savez(second / "controls.npz", **controls)
    # the reader refuses files whose digests differ from what the run recorded (one line naming the file)
    assert cli.main(["report", str(copy), "--out", str(tmp_path / "refused"), "--resamples", "50"]) == 2
    redigest(copy)  # now as if a run had written them: the sections must still not trust them
    assert cli.main(["report", str(copy), "--out", str(tmp_path / "report"), "--resamples", "50"]) == 0
    assert _rows(tmp_path / "report" / "tables" / "position_bound.csv") == []
    assert _rows(tmp_path / "report" / "tables" / "phase_steps.csv")[0]["episodes"] == "1"  # the first one is fine
    html = (tmp_path / "report" / "report.html").read_text()
    assert "id='position'" not in html and "id='phases'" in html


@pytest.mark.slow
def test_a_run_without_phases_or_controls_has_neither_section(tmp_path, fixtures_dir):
    code = cli.main(["run", "--task", "Door", "--episodes", "1", "--max-steps", "2", "--model", str(fixtures_dir / "tiny"),
                     "--out", str(tmp_path), "--run-name", "door", "--fast-render", "--png-every", "0", "--no-video"])
    assert code == 0
    row = json.loads((tmp_path / "door" / "results.jsonl").read_text())
    assert "furthest_phase" not in row  # rows of tasks without phases keep their keys
    assert cli.main(["report", str(tmp_path / "door"), "--out", str(tmp_path / "report"), "--resamples", "50"]) == 0
    html = (tmp_path / "report" / "report.html").read_text()
    assert "id='phases'" not in html and "id='position'" not in html
    assert _rows(tmp_path / "report" / "tables" / "position_bound.csv") == []


@pytest.mark.slow
def test_two_env_workers_give_the_same_phases_and_controls_bit_for_bit(run, tmp_path):
    code = cli.main(["run", "--model", str(MODEL), "--task", "Lift", "--episodes", "2", "--seed", "1", "--max-steps", "40",
                     "--attention-controls", "blank,mirror", "--controls-every", str(EVERY), "--record-inputs",
                     "--png-every", "0", "--no-video", "--fast-render", "--out", str(tmp_path), "--run-name", "workers",
                     "--workers", "2"])
    assert code == 0
    for directory in sorted(run.glob("Lift/episode_*")):
        other = tmp_path / "workers" / directory.relative_to(run)
        for name, keys in (("controls.npz", ("step", "blank", "mirror")), ("attention.npz", ("phase", "readout_attention"))):
            with np.load(directory / name) as a, np.load(other / name) as b:
                for key in keys:
                    assert np.array_equal(a[key], b[key]), (directory.name, name, key)


@pytest.mark.slow
def test_a_run_without_masks_reports_its_phases_and_says_why_nothing_is_tested(run, tmp_path):
    copy = tmp_path / "nomask"
    shutil.copytree(run, copy)
    strip_masks(copy)
    assert cli.main(["report", str(copy), "--out", str(tmp_path / "report"), "--resamples", "50"]) == 0
    assert len(_rows(tmp_path / "report" / "tables" / "phase_steps.csv")) == 3
    assert _rows(tmp_path / "report" / "tables" / "phase_tests.csv") == []
    assert "no mask measures (a run with --no-masks)" in (tmp_path / "report" / "report.html").read_text()

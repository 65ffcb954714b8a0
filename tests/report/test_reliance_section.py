"""The report's Reliance section on hand-made run folders: copies of the committed reference-lift run whose
episodes get reliance.jsonl rows and last-layer mask masses with known values; the CSV's shares, per-pixel reliance,
agreement and the disagreement sentence are checked against those values; a damaged file is a note; the section
and its table are found in the page opened in headless Chromium."""

from __future__ import annotations

import csv
import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import spearmanr

from harness.analysis.runs import load_run
from harness.probes.reliance import report as R
from tests.helpers import browser as _browser
from tests.runfolder.edits import redigest

REFERENCE = Path(__file__).resolve().parents[2] / "results" / "baselines" / "reference-lift"
REGIONS = ("target", "gripper", "arm", "task_objects", "background")
AREA = {"target": 0.05, "gripper": 0.1, "arm": 0.2, "task_objects": 0.05, "background": 0.6}
# last-layer attention mass per env mask (robot overlaps gripper and arm, and is not a region where they are):
# the remainder, task_objects, gets 1 - the regions' sum (0.15 on both cameras); no two shares of a camera tie (the
# stored masses are float32: a tie would be broken by rounding)
MASS = {"image_primary": {"target": 0.45, "gripper": 0.1, "arm": 0.05, "background": 0.25, "robot": 0.15},
        "image_wrist": {"target": 0.3, "gripper": 0.4, "arm": 0.05, "background": 0.1, "robot": 0.45}}
ATTENTION = {"image_primary": dict(zip(REGIONS, (0.45, 0.1, 0.05, 0.15, 0.25))),
             "image_wrist": dict(zip(REGIONS, (0.3, 0.4, 0.05, 0.15, 0.1)))}
RELIANCE = {  # episode -> camera -> region shares; episode 0's wrist ranks the regions as its attention does
    0: {"image_primary": dict(zip(REGIONS, (0.1, 0.6, 0.1, 0.1, 0.1))),
        "image_wrist": dict(zip(REGIONS, (0.25, 0.45, 0.02, 0.18, 0.1)))},
    1: {"image_primary": dict(zip(REGIONS, (0.3, 0.4, 0.1, 0.05, 0.15))),
        "image_wrist": dict(zip(REGIONS, (0.35, 0.4, 0.1, 0.1, 0.05)))},
}
STEPS = (0, 4, 8)  # step 8 of episode 0: the primary camera unused (shares null), left out of both


def _rows(episode: int, step: int) -> list[dict]:
    out = []
    for camera, shares in RELIANCE[episode].items():
        unused = episode == 0 and step == 8 and camera == "image_primary"
        for region, share in shares.items():
            change = 0.0 if unused else share * (1 + step)  # the per-pixel value differs by step, the share does not
            out.append({"run": "rel", "task": "Lift", "episode": episode, "seed": episode, "step": step,
                        "camera": camera, "region": region, "fill": "impute", "change": change,
                        "area_fraction": AREA[region], "reliance_per_pixel": change / AREA[region],
                        "reliance_share": None if unused else share, "camera_change": 1.0})
    return out


def _set_mass(episode_dir: Path) -> None:
    path = episode_dir / "attention.npz"
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    for camera, mass in MASS.items():
        for name, value in mass.items():
            key = f"measures/layer/mask_mass/{camera}/{name}"
            arrays[key] = arrays[key].copy()
            arrays[key][:, -1] = value  # the last layer: the one the section reads
            arrays[key][:, 0] = 0.9 if name == "background" else 0.0  # another layer: must not count
    np.savez(path, **arrays)


def _copy(to: Path, damaged: bool = True) -> Path:
    shutil.copytree(REFERENCE, to)
    for number in (0, 1):
        _set_mass(to / "Lift" / f"episode_{number}")
        (to / "Lift" / f"episode_{number}" / "reliance.jsonl").write_text(
            "".join(json.dumps(r) + "\n" for s in STEPS for r in _rows(number, s)))
    if damaged:
        (to / "Lift" / "episode_2" / "reliance.jsonl").write_text('{"step": 0, "camera": "image_primary", \n')
    results = to / "results.jsonl"
    rows = [json.loads(line) for line in results.read_text().splitlines() if line.strip()]
    for row in rows:
        if (to / row["directory"] / "reliance.jsonl").is_file():
            row["files"]["reliance.jsonl"] = {}
    results.write_text("".join(json.dumps(r) + "\n" for r in rows))
    redigest(to)
    return to


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    return _copy(tmp_path_factory.mktemp("runs") / "rel")


@pytest.fixture(scope="module")
def summary(run):
    return R.summarise([load_run(run)], resamples=500)


def _csv(summary) -> list[dict]:
    return list(csv.DictReader(io.StringIO(R.tables(summary)["reliance.csv"].decode())))


def test_the_csv_holds_known_shares_per_task_condition_camera_and_region(summary):
    rows = _csv(summary)
    assert list(rows[0]) == list(R.COLUMNS)
    assert [(r["camera"], r["region"]) for r in rows] == [(c, g) for c in ("image_primary", "image_wrist") for g in REGIONS]
    assert {(r["run"], r["task"], r["condition"], r["level"], r["episodes"]) for r in rows} == {("reference-lift", "Lift", "nominal", "0", "2")}
    for r in rows:
        camera, region = r["camera"], r["region"]
        expected = np.mean([RELIANCE[e][camera][region] for e in (0, 1)])  # episode means, then over episodes
        assert float(r["reliance_share"]) == pytest.approx(expected, abs=1e-5)
        assert float(r["attention_share"]) == pytest.approx(ATTENTION[camera][region], abs=1e-5)
        # per pixel: change / area; episode 0's primary camera has steps 0 and 4 only (step 8 unused)
        steps0 = (0, 4) if camera == "image_primary" else STEPS
        per0 = np.mean([RELIANCE[0][camera][region] * (1 + s) / AREA[region] for s in steps0])
        per1 = np.mean([RELIANCE[1][camera][region] * (1 + s) / AREA[region] for s in STEPS])
        assert float(r["reliance_per_pixel"]) == pytest.approx((per0 + per1) / 2, rel=1e-5)
    for camera in ("image_primary", "image_wrist"):
        cam = [r for r in rows if r["camera"] == camera]
        assert sum(float(r["reliance_share"]) for r in cam) == pytest.approx(1, abs=1e-5)
        assert sum(float(r["attention_share"]) for r in cam) == pytest.approx(1, abs=1e-5)
        assert cam[0]["steps"] == ("5" if camera == "image_primary" else "6")


def test_agreement_is_the_seed_mean_of_the_per_step_spearman_with_an_interval(summary):
    rows = _csv(summary)
    for camera in ("image_primary", "image_wrist"):
        r = next(r for r in rows if r["camera"] == camera)
        per_seed = [spearmanr([RELIANCE[e][camera][g] for g in REGIONS], [ATTENTION[camera][g] for g in REGIONS])[0]
                    for e in (0, 1)]
        assert float(r["spearman"]) == pytest.approx(np.mean(per_seed), abs=1e-5)
        assert r["spearman_seeds"] == "2"
        assert float(r["spearman_ci_low"]) <= float(r["spearman"]) <= float(r["spearman_ci_high"])
    wrist = next(r for r in rows if r["camera"] == "image_wrist")
    assert float(wrist["spearman"]) > 0.8  # the wrist's reliance ranks the regions as its attention does


def test_the_sentence_names_the_region_of_largest_disagreement_and_a_damaged_file_is_a_note(summary):
    rows, notes = summary
    primary = [r for r in rows if r[4] == "image_primary"]
    # |reliance - attention|: target |0.2 - 0.45| = 0.25, gripper |0.5 - 0.1| = 0.4 (the largest)
    line = R.disagreement(primary)
    assert line == ("Lift, image_primary: largest gap on gripper, 50% of the reliance against 10% of the attention "
                    "(relied on more than looked at).") and len(line.split()) <= 25
    (camera, mean, interval, seeds, steps, episodes) = R.agreement_row(primary)  # the agreement: a table row
    r = primary[0]
    assert (camera, seeds, steps, episodes) == ("image_primary", str(r[14]), str(r[10]), str(r[9]))
    assert mean == R.H.fmt(r[11], 2) and interval == f"[{R.H.fmt(r[12], 2)}, {R.H.fmt(r[13], 2)}]"
    assert len(notes) == 1 and notes[0].startswith("reference-lift/Lift/episode_2: unreadable reliance.jsonl")


def test_no_reliance_file_no_section_and_no_csv(tmp_path):
    plain = load_run(REFERENCE)
    summary = R.summarise([plain], resamples=100)
    assert summary == ([], []) and R.tables(summary) == {} and R.section(summary, None) == ""


@pytest.mark.slow
def test_the_report_shows_the_section_and_its_table_in_chromium(run, tmp_path):
    from harness import cli

    out = tmp_path / "report"
    assert cli.main(["report", str(run), "--out", str(out), "--resamples", "200"]) == 0
    table = list(csv.DictReader((out / "tables" / "reliance.csv").open()))
    assert len(table) == 10 and {r["region"] for r in table} == set(REGIONS)
    dom = _browser(out / "report.html", tmp_path, "--dump-dom").stdout
    section = re.search(r"<section id=\"reliance\">(.*?)</section>\s*(?:<section id|</main|$)", dom, re.S)
    assert section, "no Reliance section in the rendered page"
    text = section.group(1)
    assert "largest gap on gripper" in text and "<table" in text and "attention share" in text
    assert "Spearman over regions per step" in text  # the agreement: a table beside the verdict line
    assert "last layer" in text and "tables/reliance.csv" in text
    assert re.search(r"<a [^>]*href=\"#reliance\"", dom)  # an entry in the page's contents
    gripper = next(r for r in table if r["camera"] == "image_primary" and r["region"] == "gripper")
    assert f"{float(gripper['reliance_share']):.2g}" in text  # the page's number comes from the CSV


def test_eval_md_gets_a_reliance_section_with_provenance_and_keeps_the_others(run, tmp_path):
    eval_md = tmp_path / "EVAL.md"
    eval_md.write_text("# EVAL\n\n## Robustness\n\nkept\n\n## Reliance\n\nstale\n")
    assert R.main([str(run), "--eval-md", str(eval_md), "--note", "the note"]) == 0
    text = eval_md.read_text()
    assert "## Robustness\n\nkept\n" in text and "stale" not in text and text.count("## Reliance\n") == 1
    section = text[text.index("## Reliance"):]
    assert "Provenance: command" in section and "the note" in section
    assert "### Lift: nominal (run reference-lift)" in section
    assert ("- Lift, image_primary: largest gap on gripper, 50% of the reliance against 10% of the attention "
            "(relied on more than looked at).") in section
    assert "| camera | Spearman over regions per step: mean | 95% seed-cluster | seeds | steps | episodes |" in section
    assert "| image_wrist | background |" in section and "episode_2: unreadable reliance.jsonl" in section
    # the section is what its figures file renders (issue 67 item 6): the tables as rows of cells
    from harness.report import figures_file

    doc = figures_file.read(tmp_path / "figures" / "reliance.json")
    assert figures_file.render(doc) == section and doc["section"] == "## Reliance"
    tables = [b["table"] for b in doc["blocks"] if "table" in b]
    assert any(t["header"][:2] == ["camera", "Spearman over regions per step: mean"] for t in tables)
    assert any(row[:2] == ["image_wrist", "background"] for t in tables for row in t["rows"])
    # a run without reliance is one line, exit 2, EVAL.md and the figures file untouched
    before, figures_before = eval_md.read_text(), (tmp_path / "figures" / "reliance.json").read_bytes()
    assert R.main([str(REFERENCE), "--eval-md", str(eval_md)]) == 2 and eval_md.read_text() == before
    assert (tmp_path / "figures" / "reliance.json").read_bytes() == figures_before


def test_a_figures_folder_that_cannot_be_written_is_one_line_and_eval_md_stays(run, tmp_path, capsys):
    eval_md = tmp_path / "EVAL.md"
    eval_md.write_text("# EVAL\n\n## Reliance\n\nkept\n")
    (tmp_path / "figures").write_text("a file where the figures folder goes")
    assert R.main([str(run), "--eval-md", str(eval_md)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot write" in err and "figures" in err
    assert eval_md.read_text() == "# EVAL\n\n## Reliance\n\nkept\n"

"""The report's Failures section (issue 74, "why an episode failed"): one line per failed episode from diagnose's rows
and, per task, the failed episodes' stall frames beside a success at the same phase.

One real run of the reference policy (2 short Lift episodes with an MP4 and --record-inputs) is edited by hand, since
a 12-step episode never succeeds: episode 1 is marked a success, and both episodes' phases are set, so that the
failure stalls at step 6 (its first step in grasp) and the success is in grasp from step 4 to 7. Copies of it without the
MP4, without any frames and without a failure give the other cases; hand-made episodes (tests/analysis/test_diagnose.py)
give the table's cap and the choice of the pictured failures and of the success beside each."""

from __future__ import annotations

import io
import json
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from harness import cli
from harness.analysis.diagnose.failures import failure_rows
from harness.analysis.diagnose.signals import load
from harness.analysis.diagnose.outputs import SHOWN_FAILURES, failures_csv
from harness.analysis.runs import load_run
from harness.outputs.overlays import PAD
from harness.report import failure_frames as F
from harness.report import failures
from harness.report.frames import VIDEO_DISPLAY, read_video_frames
from harness.report.rundata import RunData
from tests.analysis.test_diagnose import episodes as made_episodes
from tests.helpers import REFERENCE_MODEL
from tests.runfolder.edits import drop_output, redigest

FAILED_PHASE = [0] * 6 + [1] * 6  # the failure: approach, then grasp from step 6 on (its stall step)
SUCCESS_PHASE = [0] * 4 + [1] * 4 + [2] * 4  # the success: grasp from step 4, lift from step 8


class Plots:
    """The page's figure collector, as harness.report.page._Plots: name -> PNG."""

    def __init__(self):
        self.files: dict[str, bytes] = {}
        self.captions: dict[str, str] = {}

    def add(self, name, png, alt, caption):
        self.files[name] = png
        self.captions[name] = caption
        return f"<figure data-name='{name}'></figure>"


def _edit(run: Path, episode: int, success: bool | None = None, phase: list[int] | None = None) -> None:
    directory = run / "Lift" / f"episode_{episode}"
    if phase is not None:
        with np.load(directory / "attention.npz") as z:
            arrays = {k: z[k] for k in z.files}
        arrays["phase"] = np.asarray(phase, arrays["phase"].dtype)
        np.savez(directory / "attention.npz", **arrays)
    if success is not None:
        rows = [json.loads(line) for line in (run / "results.jsonl").read_text().splitlines() if line.strip()]
        for row in rows:
            if row["episode"] == episode:
                row["success"] = success
        (run / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    redigest(run)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("failures")
    assert cli.main(["run", "--model", str(REFERENCE_MODEL), "--task", "Lift", "--episodes", "2", "--max-steps", "12",
                     "--record-inputs", "--png-every", "0", "--fast-render", "--preflight", "off", "--out", str(out),
                     "--run-name", "lift"]) == 0
    run = out / "lift"
    _edit(run, 0, phase=FAILED_PHASE)
    _edit(run, 1, success=True, phase=SUCCESS_PHASE)
    return run


def _copy(run: Path, tmp_path: Path, name: str) -> Path:
    return Path(shutil.copytree(run, tmp_path / name))


def _section(*paths: Path):
    runs = [RunData(record=load_run(p), label=p.name, colour="#000") for p in paths]
    summary = failures.summarise(runs)
    plots = Plots()
    return summary, failures.section(runs, plots, summary), plots, failures.tables(summary)


def _panel(png: bytes, row: int, left: bool, width: int) -> np.ndarray:
    """A panel of the composed figure: row `row`, the failed (left) or the successful (right) column."""
    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    top = F.TITLE + row * (F.HEADER + F.PANEL + F.ROW_GAP) + F.HEADER
    x = F.MARGIN if left else image.shape[1] - F.MARGIN - width  # one row: the right column ends at the margin
    return image[top:top + F.PANEL, x:x + width]


@pytest.mark.slow
def test_the_report_shows_the_stall_frame_from_the_mp4_beside_the_success_at_the_same_phase(run, tmp_path):
    from harness.report.build import ReportOptions, build_report

    result = build_report([run], tmp_path / "report", ReportOptions(resamples=20))
    page = result.html.read_text()
    assert "<section id='failures'><h2>Failures</h2>" in page and "href='#failures'" in page
    section = page[page.index("<section id='failures'>"):]
    table = section[section.index("<table"):section.index("</table>")]
    assert table.count("<tr>") == 2  # the header and the one failed episode
    assert ">grasp<" in table and ">6<" in table and ">row 1<" in table
    # failures.csv: diagnose's rows, byte for byte
    expected = failures_csv(failure_rows(load([run])[0])).encode()
    assert (result.out / "tables" / "failures.csv").read_bytes() == expected
    assert expected.count(b"\n") == 2 and b"lift,Lift,nominal,0,0,12,grasp,6,phases,8.0,1," in expected  # passed grasp at 8
    # the figure: one row, the failure at step 8 (the success passed grasp at 8; the failure stalled in it at 6)
    # beside the success at its last grasp step 7, from the MP4
    png = (result.out / "plots" / "failures_lift.png").read_bytes()
    image = Image.open(io.BytesIO(png))
    width = int(round((2 * VIDEO_DISPLAY + PAD) * F.PANEL / VIDEO_DISPLAY))  # camera | overlay, a square camera
    assert image.height == F.TITLE + F.HEADER + F.PANEL + F.ROW_GAP and image.width >= 2 * width + F.GAP
    failed, success = (load_run(run).episodes[k] for k in (0, 1))
    crop = (VIDEO_DISPLAY, 2 * VIDEO_DISPLAY + PAD)
    stall = F._fit(read_video_frames(failed.video_path, [8], *crop)[8])
    assert stall.shape == (F.PANEL, width, 3)
    assert np.array_equal(_panel(png, 0, True, width), stall)
    assert not np.array_equal(stall, F._fit(read_video_frames(failed.video_path, [6], *crop)[6]))  # step 8, not 6
    assert np.array_equal(_panel(png, 0, False, width), F._fit(read_video_frames(success.video_path, [7], *crop)[7]))
    caption = re.search(r"<figcaption>([^<]*\(plots/failures_lift.png\))</figcaption>", section).group(1)
    assert "each stalled in its furthest phase (left: at the step the successes had passed that phase" in caption
    assert "rollout.mp4" in caption


@pytest.mark.slow
def test_the_section_is_deterministic_and_reads_inputs_npz_without_an_mp4(run, tmp_path):
    """The same runs give the same HTML and PNG bytes; without rollout.mp4 the frames come from inputs.npz (the
    policy's input frame beside it with the last layer's head-mean attention drawn over it)."""
    first, second = _section(run), _section(run)
    assert first[1] == second[1] and first[2].files == second[2].files and first[3] == second[3]
    assert "seed 1 ep. 1 (rollout.mp4)" not in first[1]  # the headers are in the PNG, not the HTML
    copy = _copy(run, tmp_path, "inputs_only")
    for video in copy.glob("Lift/episode_*/rollout.mp4"):
        video.unlink()
    summary, html, plots, tables = _section(copy)
    (png,) = plots.files.values()
    width = 2 * F.PANEL + PAD  # a 128 px square camera at PANEL px, beside its overlay
    with np.load(copy / "Lift" / "episode_0" / "inputs.npz") as z:
        frame = F._fit(z["input/image_primary"][8])
    left = _panel(png, 0, True, width)
    assert np.array_equal(left[:, :F.PANEL], frame)  # the input frame at the step shown
    assert not np.array_equal(left[:, F.PANEL + PAD:], frame)  # the overlay drawn over it
    assert F.panels(*summary.where[("inputs_only", "Lift", 0)], [8])[8][1] == "inputs.npz"
    assert "inputs.npz" in next(iter(plots.captions.values()))


@pytest.mark.slow
def test_without_frames_the_table_stays_and_one_line_says_how_to_get_them(run, tmp_path):
    copy = _copy(run, tmp_path, "no_frames")
    for video in copy.glob("Lift/episode_*/rollout.mp4"):
        video.unlink()
    drop_output(copy, "inputs.npz")
    summary, html, plots, tables = _section(copy)
    assert plots.files == {} and len(summary.rows) == 1 and html.count("<tr>") == 2
    assert "Lift: no frames were recorded for its failed episodes" in html
    assert "run without --no-video, or with --record-inputs" in html
    assert list(tables) == ["failures.csv"]


@pytest.mark.slow
def test_the_section_is_absent_without_a_failure(run, tmp_path):
    copy = _copy(run, tmp_path, "all_succeed")
    _edit(copy, 0, success=True)
    summary, html, plots, tables = _section(copy)
    assert summary is None and html == "" and plots.files == {} and tables == {}


# ------------------------------------------------------------------------------------------- hand-made episodes


def _made_summary(tmp_path: Path, framed: set[str]) -> tuple[failures.Summary, list]:
    """test_diagnose's hand-made episodes (3 runs, one condition each, 30 seeds) as a Summary, and the runs; episodes
    of the runs in `framed` have a (dummy) rollout.mp4."""
    made = made_episodes("noise", seeds=30)
    runs = {name: SimpleNamespace(label=name, record=SimpleNamespace(attention=True, tasks=("Lift",)))
            for name in dict.fromkeys(e.run for e in made)}
    where = {}
    for e in made:
        directory = tmp_path / e.run / f"episode_{e.seed}"
        where[(e.run, e.task, e.episode)] = (runs[e.run], SimpleNamespace(
            video_path=directory / "rollout.mp4" if e.run in framed else None, directory=directory))
    return failures.Summary(failure_rows(made), made, where), list(runs.values())


def test_the_table_is_capped_and_the_rest_is_named(tmp_path):
    summary, runs = _made_summary(tmp_path, framed=set())
    plots = Plots()
    html = failures.section(runs, plots, summary)
    failed = sum(not e.success for e in summary.episodes)
    assert failed > SHOWN_FAILURES
    assert html.count("<tr>") == 1 + SHOWN_FAILURES
    assert f"{failed - SHOWN_FAILURES} more failed episodes of Lift in tables/failures.csv" in html
    assert f"{failed} of 90 finished episodes of Lift failed" in html
    assert "no frames were recorded" in html and plots.files == {}


def test_the_pictured_failures_are_the_furthest_from_the_successes_and_each_gets_a_success_of_its_run(tmp_path):
    summary, _ = _made_summary(tmp_path, framed={"run0", "run2"})
    rows = [r for r in summary.rows if r["task"] == "Lift"]
    chosen = failures.pictured(rows, summary)
    assert len(chosen) == failures.PICTURED and {r["run"] for r in chosen} <= {"run0", "run2"}  # with frames only
    largest = [failures._largest_z(r) for r in chosen]
    others = [failures._largest_z(r) for r in rows if r not in chosen and r["run"] != "run1"]
    assert largest == sorted(largest, reverse=True) and min(largest) >= max(others)
    failed = next(e for e in summary.episodes if e.run == "run0" and not e.success)
    match = failures.success_for(failed, summary)
    assert match.tier == 0 and match.episode.run == "run0" and match.episode.success
    assert match.episode.phase[match.step] == failed.phase.max() == 1 and match.episode.phase[match.step + 1] == 2
    row = next(r for r in summary.rows if (r["run"], r["episode"]) == (failed.run, failed.episode))
    step = failures.shown_step(row, failed)  # where the successes had moved on, not before the stall
    assert int(row["stall_step"]) <= step == min(max(int(row["stall_step"]), round(float(row["passed_median"]))),
                                                 failed.steps - 1)
    # without a framed success of its own condition: another condition's, said so
    summary, _ = _made_summary(tmp_path, framed={"run2"})
    match = failures.success_for(failed, summary)
    assert match.tier == 2 and match.episode.run == "run2" and failures.TIERS[2] == "another condition"


def test_a_frame_not_recorded_is_the_last_one_before_it():
    assert F.at_or_before(list(range(20)), 26) == 19 and F.at_or_before([5, 6], 2) == 5 and F.at_or_before([], 7) == 7
    assert F.at_or_before([0, 4, 8], 6) == 4


def test_the_committed_baseline_shows_its_failure_from_its_inputs_cut_short(tmp_path):
    """results/baselines/reference-lift records inputs.npz for the first 20 steps only: its one failure (seed 2,
    stalled in approach from step 0, the successes past it at step 26) is shown at step 19, its last frame."""
    from harness.report.build import ReportOptions, build_report

    baseline = Path(__file__).resolve().parents[2] / "results" / "baselines" / "reference-lift"
    result = build_report([baseline], tmp_path / "report", ReportOptions(resamples=20))
    png = (result.out / "plots" / "failures_lift.png").read_bytes()
    failed = next(e for e in load_run(baseline).episodes if not e.success)
    assert F.recorded_steps(failed)[-1] == 19 < failed.steps - 1
    width = 2 * F.PANEL + PAD
    with np.load(failed.directory / "inputs.npz") as z:
        frame = F._fit(z["input/image_primary"][19])
    assert np.array_equal(_panel(png, 0, True, width)[:, :F.PANEL], frame)


@pytest.mark.slow
def test_a_damaged_episode_is_left_out_with_a_note_and_the_section_stays(run, tmp_path):
    """A hostile edit the run store's checks let through: the successful episode's phase array cut to 3 of its 12
    steps (digests rewritten to match). The failure stays in the table, the damaged success is named in a note, and
    the figure says no success could be shown rather than failing. (Bytes that are no archive are refused when the
    run loads, in one line, before any section: harness.runfolder.integrity.)"""
    copy = _copy(run, tmp_path, "damaged")
    _edit(copy, 1, phase=[0, 1, 2])
    summary, html, plots, tables = _section(copy)
    assert [r["episode"] for r in summary.rows] == [0] and tables["failures.csv"].count(b"\n") == 2
    assert any(n.startswith("damaged/Lift/episode_1: left out (") for n in summary.notes), summary.notes
    assert "damaged/Lift/episode_1: left out" in html
    assert "no episode of Lift succeeded" in next(iter(plots.captions.values()))

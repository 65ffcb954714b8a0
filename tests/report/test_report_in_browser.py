"""`octo-harness report` on real short runs (real simulator, the reference fixture checkpoint, real MP4s), checked in a
real headless Chromium: the page renders, its sections are there and every inlined image decodes."""

import base64
import csv
import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from harness import cli
from harness.analysis.aggregate import TABLE_COLUMNS
from tests.report.text_overlap import drawn_texts, overlaps
from tests.runfolder.edits import redigest, rehash, strip_masks
from tests.helpers import browser as _browser

pytestmark = pytest.mark.slow

STEPS = 3






def _run(fixtures_dir, out: Path, name: str, tasks: str, episodes: int, steps: int) -> Path:
    code = cli.main(["run", "--task", tasks, "--episodes", str(episodes), "--max-steps", str(steps), "--model",
                     str(fixtures_dir / "tiny"), "--out", str(out), "--run-name", name, "--fast-render", "--png-every", "0"])
    assert code == 0
    return out / name


@pytest.fixture(scope="module")
def runs(fixtures_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs")
    full = _run(fixtures_dir, out, "full", "Lift,Stack", 2, STEPS)
    # `full` as a --no-masks run writes it (no mask arrays), without paying for a second model load and compile
    nomask = _copy(full, out / "nomask")
    strip_masks(nomask)
    # an interrupted copy of `full`: the last job has no result yet, one episode failed, and the model is marked random
    partial = _copy(full, out / "partial")
    rows = [json.loads(line) for line in (partial / "results.jsonl").read_text().splitlines()][:3]
    rows[1].update(status="failed", success=False, error="RuntimeError: simulated crash")
    (partial / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (partial / "results.json").write_text(json.dumps({"status": "interrupted"}))
    manifest = json.loads((partial / "manifest.json").read_text())
    manifest["model"]["is_random"] = True
    (partial / "manifest.json").write_text(json.dumps(manifest))
    return full, partial, nomask


def _copy(run: Path, to: Path) -> Path:
    shutil.copytree(run, to)
    manifest = json.loads((to / "manifest.json").read_text())
    manifest["run"] = to.name
    (to / "manifest.json").write_text(json.dumps(manifest))
    return to


@pytest.fixture(scope="module")
def report(runs, tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "rep"
    assert cli.main(["report", *map(str, runs), "--out", str(out), "--resamples", "500"]) == 0
    return out


def _table(path: Path) -> list[dict]:
    return list(csv.DictReader(path.open()))


def test_tables_are_long_format_and_agree_with_the_episode_metrics(runs, report):
    layers = _table(report / "tables" / "layers.csv")
    assert tuple(layers[0])[: len(TABLE_COLUMNS)] == TABLE_COLUMNS
    heads = _table(report / "tables" / "heads.csv")
    assert {r["head"] for r in heads if r["run"] == "full"} == {"0", "1", "2", "3"}
    # head-mean target mass of `full`, Lift, all episodes = mean over episodes of the per-step values in attention.npz
    full = runs[0]
    expected = []
    for k in range(2):
        with np.load(full / "Lift" / f"episode_{k}" / "attention.npz") as z:
            expected.append(np.nanmean(z["metrics/mask_mass/image_primary/target"], axis=0))  # (layers,)
    expected = np.mean(expected, axis=0)
    got = {int(r["layer"]): float(r["value"]) for r in layers if (r["run"], r["task"], r["outcome"], r["metric"]) ==
           ("full", "Lift", "all", "mask_mass/image_primary/target")}
    np.testing.assert_allclose([got[i] for i in range(len(expected))], expected, rtol=2e-3)
    success = {(r["run"], r["task"]): r for r in _table(report / "tables" / "success.csv")}
    assert success[("full", "Lift")]["n"] == "2" and success[("partial", "Lift")]["errored"] == "1"
    assert success[("partial", "Stack")]["missing"] == "1"
    progress = _table(report / "tables" / "progress.csv")
    assert {"bin", "progress_from", "progress_to"} <= set(progress[0])


def test_partial_failed_random_and_maskless_runs_are_reported_as_such(report):
    page = (report / "report.html").read_text()
    assert "partial was interrupted: 1 of 4 episodes missing (Stack: 1)" in page
    assert "RuntimeError: simulated crash" in page
    assert page.count("RANDOM WEIGHTS") >= 2 and "partial: RANDOM WEIGHTS" in page and "full: RANDOM WEIGHTS" not in page
    assert "nomask recorded no target masks" in page
    layers = _table(report / "tables" / "layers.csv")
    assert not [r for r in layers if r["run"] == "nomask" and r["metric"].startswith("mask_")]  # absent, not zero
    assert [r for r in layers if r["run"] == "nomask" and r["metric"] == "share/primary"]


def test_videos_are_linked_relatively_and_images_are_inlined(report):
    page = (report / "report.html").read_text()
    sources = re.findall(r"<video [^>]*src='([^']+)'", page)
    assert len(sources) == 4 + 2 + 4  # full: 4 episodes, partial: 2 finished ok (no video for the failed one), nomask: 4
    for src in sources:
        assert not src.startswith(("/", "file:", "http")) and (report / src).is_file(), src
    images = re.findall(r"<img src='data:image/png;base64,([^']+)'", page)
    assert len(images) == len(list((report / "plots").glob("*.png"))) > 5
    for data in images:
        Image.open(io.BytesIO(base64.b64decode(data))).verify()
    assert "http://" not in page and "https://" not in page  # nothing fetched from the network


def test_report_renders_in_headless_chromium(report, tmp_path):
    html = report / "report.html"
    shot = tmp_path / "shot.png"
    _browser(html, tmp_path, f"--screenshot={shot}", "--window-size=1280,1600")
    pixels = np.asarray(Image.open(shot).convert("L"), np.float32)
    assert pixels.std() > 20 and (pixels < 200).mean() > 0.02  # not blank
    dom = _browser(html, tmp_path, "--dump-dom", "--virtual-time-budget=10000").stdout
    for title in ("Cross-task comparison", "Task: Lift", "Task: Stack", "Run manifest", "Manifest: full"):
        assert f">{title}</h" in dom, title
    total = re.search(r'data-images-total="(\d+)"', dom)
    ok = re.search(r'data-images-ok="(\d+)"', dom)
    assert total and ok, "the page's image check did not run"
    assert int(ok.group(1)) == int(total.group(1)) > 5


def test_runs_without_stored_measures_give_the_same_tables(runs, report, tmp_path):
    """Older runs have no measures/* arrays: the report measures readout_attention itself, with the same result
    (and the same seeded bootstrap intervals)."""
    copies = []
    for run in runs:
        copy = shutil.copytree(run, tmp_path / run.name)
        for npz in copy.glob("*/episode_*/attention.npz"):
            with np.load(npz) as z:
                assert any(k.startswith("measures/head/") for k in z.files)  # the writers store them
                kept = {k: z[k] for k in z.files if not k.startswith("measures/")}
            np.savez(npz, **kept)
        redigest(copy)
        copies.append(copy)
    out = tmp_path / "again"
    assert cli.main(["report", *map(str, copies), "--out", str(out), "--resamples", "500", "--workers", "1"]) == 0
    for name in ("layers.csv", "heads.csv", "progress.csv"):
        a, b = _table(report / "tables" / name), _table(out / "tables" / name)
        assert [r["metric"] for r in a] == [r["metric"] for r in b] and len(a) > 10, name
        for column in ("value", "ci_low", "ci_high"):
            x = np.array([float(r[column] or "nan") for r in a])
            y = np.array([float(r[column] or "nan") for r in b])
            np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-6, err_msg=f"{name}:{column}")


def test_not_a_run_is_one_line_and_exit_2(runs, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert cli.main(["report", str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "is not an octo-harness run folder" in err
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    assert cli.main(["report", str(runs[0]), "--out", str(tmp_path / "mine")]) == 2  # not a report folder: untouched
    assert "refusing to replace" in capsys.readouterr().err
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"


def _only(run: Path, to: Path, task: str) -> Path:
    """A copy of `run` holding one of its tasks, as a run of that task alone writes it."""
    copy = _copy(run, to)
    rows = [json.loads(line) for line in (copy / "results.jsonl").read_text().splitlines()]
    (copy / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows if r["task"] == task))
    for other in {r["task"] for r in rows} - {task}:
        shutil.rmtree(copy / other)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["protocol"]["tasks"] = [task]
    manifest["jobs"] = [job for job in manifest["jobs"] if job[0] == task]
    (copy / "manifest.json").write_text(json.dumps(manifest))
    (copy / "results.json").unlink(missing_ok=True)
    rehash(copy)
    return copy


@pytest.fixture(scope="module")
def mixed(runs, tmp_path_factory):
    """The report of three runs holding different tasks (Lift, Stack, and Lift again under another name, as a 64 px
    model's run would), with the text every matplotlib figure drew and its extents at draw time."""
    out = tmp_path_factory.mktemp("mixed")
    held = [_only(runs[0], out / name, task) for name, task in (("lift", "Lift"), ("stack", "Stack"),
                                                                ("lift-64px", "Lift"))]
    with drawn_texts() as texts:
        assert cli.main(["report", *map(str, held), "--out", str(out / "rep"), "--resamples", "200"]) == 0
    return out / "rep", texts


def test_runs_of_different_tasks_draw_a_panel_per_task_and_no_figure_text_overlaps(mixed):
    report, texts = mixed
    assert len(texts) >= 8  # every figure the report draws
    for drawn in texts.values():
        assert not overlaps(drawn), overlaps(drawn)
    drawn = [t for figure in texts.values() for t, _ in figure]
    assert "n/a" not in drawn  # no panel of absent cells: each task's panel holds the runs that hold it
    assert drawn.count("Lift") >= 2 and drawn.count("Stack") >= 2  # per-task panel titles (lift, shares)


# Every shown text node's boxes (one per line box; a closed <details>' content is not shown); the pairs of different nodes whose boxes intersect by over 1 px in both
# directions are written to <body data-text-overlaps> (the first few, as text) once the images have laid out.
_OVERLAP_SCRIPT = """<script>
window.addEventListener('load', function () {
  var boxes = [], walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT), node, found = [];
  while ((node = walker.nextNode())) {
    if (!node.textContent.trim() || !node.parentElement.checkVisibility({visibilityProperty: true})) continue;
    var range = document.createRange(); range.selectNodeContents(node);
    Array.prototype.forEach.call(range.getClientRects(), function (r) {
      if (r.width > 0 && r.height > 0) boxes.push({n: node, r: r, t: node.textContent.trim().slice(0, 40)});
    });
  }
  for (var i = 0; i < boxes.length; i++) for (var j = i + 1; j < boxes.length; j++) {
    var a = boxes[i], b = boxes[j];
    if (a.n === b.n) continue;
    var dx = Math.min(a.r.right, b.r.right) - Math.max(a.r.left, b.r.left);
    var dy = Math.min(a.r.bottom, b.r.bottom) - Math.max(a.r.top, b.r.top);
    if (dx > 1 && dy > 1) found.push(a.t + ' | ' + b.t);
  }
  document.body.setAttribute('data-text-boxes', String(boxes.length));
  document.body.setAttribute('data-text-overlaps', found.slice(0, 5).join(' ;; ') || 'none');
});
</script>"""


@pytest.mark.parametrize("width", [1280, 800])
def test_page_text_does_not_overlap_in_chromium(mixed, tmp_path, width):
    report, _ = mixed
    page = report / f"checked_{width}.html"  # beside report.html: its relative video links still resolve
    page.write_text((report / "report.html").read_text().replace("</body>", _OVERLAP_SCRIPT + "</body>"))
    dom = _browser(page, tmp_path, f"--window-size={width},1000", "--dump-dom", "--virtual-time-budget=10000").stdout
    boxes = re.search(r'data-text-boxes="(\d+)"', dom)
    assert boxes and int(boxes.group(1)) > 200, "the overlap check did not run"
    assert 'data-text-overlaps="none"' in dom, re.search(r'data-text-overlaps="([^"]*)"', dom).group(1)

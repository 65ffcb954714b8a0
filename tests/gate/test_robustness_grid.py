"""Perturbed runs end to end with the reference policy (real simulator, real JAX model, real chromium).

Known answers: a run at level 0 is the plain run (same protocol hash, same actions bit for bit); a perturbed protocol
gives the same actions and inputs sequentially and with two env workers; a paraphrase is what the model receives
(inputs.npz) and what the manifest and episode.json record; with mask-all@image_primary (mean fill) a primary-camera
shift moves the step-0 chunk at least 10x less than without it (measured: 0.0125 vs 0.348, 28x), a wrist shift more; `octo-harness robustness` runs a grid, resumes it
without re-running anything, and `octo-harness report` adds a Robustness section whose tables agree with the runs.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

import envs
from harness.policies import as_policy
from harness import cli
from harness.run import execute
from harness.run.settings import build_protocol
from harness.run.workers import WorkersExecutor
from tests.helpers import browser

REPO = Path(__file__).resolve().parents[2]
MODEL = REPO / "models" / "octo-reference-robosuite"
STEPS = 3


@pytest.fixture(scope="module")
def model():
    from harness.octo import load_pretrained

    return load_pretrained(str(MODEL))


@pytest.fixture(scope="module")
def nominal(model, tmp_path_factory):
    """The unperturbed run (2 episodes, 3 steps), made once and only read: the plain run the level-0, two-worker
    and mask-all tests hold their perturbed runs against."""
    return execute(_protocol(), tmp_path_factory.mktemp("nominal"), "plain", model=model, progress=False)


def _protocol(**settings):
    base = {"model": str(MODEL), "task": ["Lift"], "episodes": 2, "max_steps": STEPS, "fast_render": True,
            "png_every": 0, "no_video": True, "seed": 100}
    return build_protocol({**base, **settings})


def _actions(run: Path, task: str = "Lift") -> dict:
    out = {}
    for episode in sorted((run / task).glob("episode_*")):
        with np.load(episode / "actions.npz") as z:
            out[episode.name] = {k: z[k] for k in z.files}
    assert out, f"no episodes in {run}"
    return out


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(
        a[e].keys() == b[e].keys() and all(np.array_equal(a[e][k], b[e][k]) for k in a[e]) for e in a)


@pytest.mark.slow
def test_level_zero_run_is_the_plain_run(model, nominal, tmp_path):
    plain = nominal
    zero = execute(_protocol(perturb="camera:0,noise:0"), tmp_path, "zero", model=model, progress=False)
    assert plain.manifest["protocol_hash"] == zero.manifest["protocol_hash"]
    assert "perturb" not in zero.manifest["protocol"]
    assert _same(_actions(plain.run_dir), _actions(zero.run_dir))


@pytest.mark.slow
def test_perturbed_protocol_is_bit_identical_with_two_workers(model, nominal, tmp_path):
    protocol = _protocol(perturb="camera:2,noise:2,distractors:1")
    sequential = execute(protocol, tmp_path / "a", "run", model=model, progress=False)
    parallel = execute(protocol, tmp_path / "b", "run", model=model, progress=False,
                       executor=lambda context, m: WorkersExecutor(context, as_policy(m), workers=2))
    a, b = _actions(sequential.run_dir), _actions(parallel.run_dir)
    assert _same(a, b)
    assert not _same(a, _actions(nominal.run_dir))  # the perturbation did change what the policy was fed
    drawn = json.loads((sequential.run_dir / "Lift" / "episode_0" / "episode.json").read_text())["perturbation"]
    assert set(drawn) == {"camera@image_primary", "distractors", "noise"}


@pytest.mark.slow
def test_a_paraphrase_is_what_the_model_receives_and_what_is_recorded(model, tmp_path):
    summary = execute(_protocol(perturb="language:2", record_inputs=True), tmp_path, "lang", model=model, progress=False)
    assert summary.manifest["protocol"]["perturb"] == "language:2"
    paraphrases = envs.get_task("Lift").paraphrases
    for episode in sorted((summary.run_dir / "Lift").glob("episode_*")):
        meta = json.loads((episode / "episode.json").read_text())
        assert meta["instruction"] in paraphrases and meta["perturbation"]["instruction"] == meta["instruction"]
        with np.load(episode / "inputs.npz") as z:
            assert str(z["instruction"]) == meta["instruction"]


def _step0_change(a: dict, b: dict) -> float:
    """Largest change of the step-0 predicted chunk between two runs of the same seeds (the scenes are the same
    until then: only what the policy saw differs)."""
    return max(float(np.abs(a[e]["predicted"][0] - b[e]["predicted"][0]).max()) for e in a)


@pytest.mark.slow
def test_mask_all_primary_makes_actions_blind_to_a_primary_camera_shift(model, nominal, tmp_path):
    """mask-all fills every patch with the frame's per-channel mean (harness.interventions), so of the primary camera
    the policy still sees three numbers, its mean colour; a shift changes those slightly. Known answer: the step-0
    chunk moves at least 10x less with the camera masked than without, and the same masked frame gives the same
    actions bit for bit.

    Only the step-0 chunk is compared (`_step0_change`), which the policy predicts from the scene as reset, before
    any later step exists: so these runs stop after that step (1 step, not 3; same seeds), and the unmasked shifted
    run is still held against the 3-step nominal run's step 0."""
    def run(name, **extra):
        return _actions(execute(_protocol(max_steps=1, **extra), tmp_path, name, model=model, progress=False).run_dir)

    masked, masked_shift = run("masked", intervene="mask-all@image_primary"), \
        run("masked_shift", intervene="mask-all@image_primary", perturb="camera:5")
    plain, shifted = _actions(nominal.run_dir), run("shift", perturb="camera:5")
    blind, seeing = _step0_change(masked, masked_shift), _step0_change(plain, shifted)
    print(f"step-0 chunk change under camera:5: masked {blind:.3g}, unmasked {seeing:.3g}")
    assert seeing > 0 and blind < 0.1 * seeing, (blind, seeing)
    wrist = run("masked_wrist_shift", intervene="mask-all@image_primary", perturb="camera@image_wrist:5")
    assert _step0_change(masked, wrist) > blind  # the wrist camera it still sees does move the actions


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_robustness_grid_resumes_and_reports_in_chromium(tmp_path, capsys):
    out = tmp_path / "grid"
    argv = ["robustness", "--model", str(MODEL), "--task", "Lift", "--perturb", "distractors,lighting", "--levels", "0,2",
            "--episodes", "2", "--max-steps", str(STEPS), "--fast-render", "--no-video", "--out", str(out)]
    assert cli.main(argv) == 0
    grid = json.loads((out / "robustness.json").read_text())
    assert grid["runs"] == {"nominal": None, "distractors-2": "distractors:2", "lighting-2": "lighting:2"}
    capsys.readouterr()
    assert cli.main(argv) == 0  # resumed: every run is already complete
    assert "complete" in capsys.readouterr().out
    for name in grid["runs"]:
        assert len((out / name / "results.jsonl").read_text().splitlines()) == 2

    runs = [str(out / name) for name in grid["runs"]]
    assert cli.main(["report", *runs, "--out", str(out / "report")]) == 0
    tables = out / "report" / "tables"
    success = _rows(tables / "robustness.csv")
    cells = {(r["condition"], int(r["level"])): r for r in success}
    assert set(cells) == {("distractors", 0), ("distractors", 2), ("lighting", 0), ("lighting", 2)}
    assert all(int(r["n"]) == 2 for r in success)
    assert float(cells[("distractors", 2)]["distractor_mass"]) > 0 and float(cells[("distractors", 0)]["distractor_mass"]) == 0
    shift = _rows(tables / "robustness_shift.csv")
    assert len(shift) == 2 * 2 * 4  # perturbed runs x episodes x layers of the reference policy
    assert all(float(r["js_bits"]) >= 0 for r in shift) and any(float(r["js_bits"]) > 0 for r in shift)
    assert _rows(tables / "robustness_association.csv")[0]["task"] == "Lift"
    paired = {r["run"]: r for r in _rows(tables / "robustness_paired.csv")}
    assert set(paired) == {"distractors-2", "lighting-2"} and all(int(r["pairs"]) == 2 for r in paired.values())

    dom = browser(out / "report" / "report.html", tmp_path, "--dump-dom", "--virtual-time-budget=10000").stdout
    assert ">Robustness</h2>" in dom and "point-biserial" in dom and "plots/robustness_lift.png" in dom
    assert "Holm p" in dom and "seed-cluster 95%" in dom

    # the EVAL.md command (scripts/robustness_reference.sh): the section made once, written and printed; run twice it
    # replaces its section, not appends a second
    from harness.report.robustness import main as robustness_main

    eval_md = tmp_path / "EVAL.md"
    eval_md.write_text("# model: evaluation\n\ntable\n\n## Faithfulness\n\nkept\n")
    assert robustness_main([*runs, "--eval-md", str(eval_md), "--note", "made by a test"]) == 0
    capsys.readouterr()
    assert robustness_main([*runs, "--eval-md", str(eval_md), "--note", "made by a test"]) == 0
    printed, text = capsys.readouterr().out, eval_md.read_text()
    assert text.count("## Robustness") == 1 and "## Faithfulness\n\nkept" in text and "made by a test" in text
    assert printed.strip() in text
    assert text.count("\nProvenance: command `python -m harness.report.robustness ") == 1  # its own line, once
    level2 = next(r for r in success if r["condition"] == "distractors" and r["level"] == "2")
    assert f"| distractors | 2 | {level2['successes']}/2 |" in text
    # a second grid goes under its own heading (--section): the first grid's section stays as it was
    assert robustness_main([*runs, "--eval-md", str(eval_md), "--section", "Robustness of the wrist camera"]) == 0
    capsys.readouterr()
    second = eval_md.read_text()
    assert second.startswith(text.rstrip("\n")) and second.count("\n## Robustness of the wrist camera\n") == 1
    assert "--section 'Robustness of the wrist camera'" in second[len(text):]  # the provenance names the option
    from harness.report import figures_file  # each section is what its figures file beside EVAL.md renders

    for name, heading in (("robustness", "## Robustness"), ("robustness-of-the-wrist-camera",
                                                           "## Robustness of the wrist camera")):
        rendered = figures_file.render(figures_file.read(tmp_path / "figures" / f"{name}.json"))
        assert rendered.startswith(heading + "\n") and rendered in second
    text = second
    # an unperturbed run alone is one line and leaves EVAL.md as it was
    nominal = next(r for r in runs if Path(r).name == "nominal")
    assert robustness_main([nominal, "--eval-md", str(eval_md)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no run here was perturbed" in err and eval_md.read_text() == text

    # regress over the grid with the same model: every condition's pairs are identical, the gate passes
    assert cli.main(["regress", "--baseline", str(out), "--model", str(MODEL), "--out", str(tmp_path / "reg"),
                     "--run-name", "cand"]) == 0
    printed = capsys.readouterr().out
    assert "regress (grid): IDENTICAL over 3 condition(s)" in printed, printed
    regress_json = json.loads((tmp_path / "reg" / "cand" / "regress" / "regress.json").read_text())
    assert set(regress_json["conditions"]) == set(grid["runs"])
    assert all(c["alpha"] == pytest.approx(0.05 / 3, rel=1e-4) for c in regress_json["conditions"].values())
    # compare renders the step-0 frames of each condition's perturbed scene
    assert cli.main(["compare", str(out), str(tmp_path / "reg" / "cand"), "--out", str(tmp_path / "cmp")]) == 0
    assert (tmp_path / "cmp" / "compare.html").is_file()

"""Every malformed run folder is one line and exit 2, from every command that reads one (run --resume, report,
compare, regress, replay): the manifest and the rows are checked in one place (harness/runfolder/schema.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from harness.cli import main
from harness.runfolder.schema import MalformedRunError, check_manifest, check_row
from tests.runfolder.edits import rehash

REPO = Path(__file__).resolve().parents[2]
BASELINE = REPO / "results" / "baselines" / "reference-lift"


def _manifest(run: Path) -> dict:
    return json.loads((run / "manifest.json").read_text())


def _set(run: Path, change) -> None:
    manifest = _manifest(run)
    change(manifest)
    (run / "manifest.json").write_text(json.dumps(manifest))


MANIFEST_DAMAGE = {
    "protocol a string": (lambda m: m.update(protocol="Lift"), "protocol must be an object"),
    "model a number": (lambda m: m.update(model=3), "model must be an object"),
    "protocol.model a number": (lambda m: m["protocol"].update(model=3), "protocol.model must be a model source"),
    "protocol.tasks a number": (lambda m: m["protocol"].update(tasks=3), "protocol.tasks must be a non-empty list"),
    "jobs a string": (lambda m: m.update(jobs="x"), "jobs must be a non-empty list"),
    "a job of another task": (lambda m: m["jobs"].__setitem__(0, ["Door", 0, 0]), "names a task that protocol.tasks"),
    "too many jobs": (lambda m: m["jobs"].append(["Lift", 8, 8]), "jobs holds 9 episodes but protocol asks for"),
    "episodes a string": (lambda m: m["protocol"].update(episodes="2"), "protocol.episodes must be an integer"),
    "policy a list": (lambda m: m["protocol"].update(policy=[1]), "protocol.policy must be an object"),
}
ROW_DAMAGE = {
    "a middle line not JSON": (lambda lines: [lines[0][:-3], *lines[1:]], "line 1: not JSON"),
    "episode a string": (lambda lines: [lines[0].replace('"episode": 0', '"episode": "0"'), *lines[1:]],
                         "episode must be an integer"),
    "a job the manifest lacks": (lambda lines: [lines[0].replace('"episode": 0', '"episode": 9'), *lines[1:]],
                                 "is not one of the manifest's jobs"),
    "status unknown": (lambda lines: [lines[0].replace('"status": "ok"', '"status": "fine"'), *lines[1:]],
                       "status must be one of"),
}


@pytest.fixture()
def runs(tmp_path):
    good, bad = tmp_path / "good", tmp_path / "bad"
    for run in (good, bad):
        shutil.copytree(BASELINE, run)
        # the committed manifest names the model where the baseline was made; this checkout's copy is the same files
        _set(run, lambda m: m["protocol"].update(model=str(REPO / "models" / "octo-reference-robosuite")))
        rehash(run)
    return good, bad


def _commands(good: Path, bad: Path, tmp: Path) -> dict[str, list[str]]:
    return {
        "run --resume": ["run", "--resume", str(bad)],
        "report": ["report", str(bad), "--out", str(tmp / "report")],
        "compare (candidate)": ["compare", str(good), str(bad), "--out", str(tmp / "cmp")],
        "compare (baseline)": ["compare", str(bad), str(good), "--out", str(tmp / "cmp")],
        "regress --baseline": ["regress", "--baseline", str(bad), "--model", "models/octo-reference-robosuite",
                               "--out", str(tmp / "reg")],
        "replay": ["replay", str(bad), "--model", str(REPO / "models" / "octo-reference-robosuite"), "--out", str(tmp / "replay")],
    }


def _one_line_exit_2(argv, capsys, expected: str) -> None:
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, (argv[0], err)
    assert len(err) == 1 and err[0].startswith("error: ") and expected in err[0], err
    assert "re-create the run" in err[0] or "--overwrite" in err[0]


@pytest.mark.parametrize("damage", sorted(MANIFEST_DAMAGE))
def test_a_manifest_with_wrong_types_is_one_line_and_exit_2_everywhere(damage, runs, tmp_path, capsys):
    good, bad = runs
    change, expected = MANIFEST_DAMAGE[damage]
    _set(bad, change)
    for name, argv in _commands(good, bad, tmp_path).items():
        _one_line_exit_2(argv, capsys, expected)
    assert not (tmp_path / "reg").exists() and not (tmp_path / "report").exists()  # nothing ran, nothing written


@pytest.mark.parametrize("damage", sorted(ROW_DAMAGE))
def test_a_malformed_results_row_is_one_line_and_exit_2_everywhere(damage, runs, tmp_path, capsys):
    good, bad = runs
    change, expected = ROW_DAMAGE[damage]
    lines = (bad / "results.jsonl").read_text().splitlines()
    (bad / "results.jsonl").write_text("\n".join(change(lines)) + "\n")
    for name, argv in _commands(good, bad, tmp_path).items():
        if name == "regress --baseline" and damage == "a job the manifest lacks":
            continue  # the baseline's rows are read by load_run like compare's: covered there
        _one_line_exit_2(argv, capsys, expected)


def test_a_torn_last_line_is_a_row_being_appended_not_damage(runs):
    from harness.analysis.runs import load_run

    _, bad = runs
    text = (bad / "results.jsonl").read_text()
    (bad / "results.jsonl").write_text(text + '{"task": "Lift", "episo')
    assert len(load_run(bad).episodes) == 8


def test_the_schema_accepts_what_the_store_writes_and_names_the_field_it_refuses():
    manifest = _manifest(BASELINE)
    assert check_manifest(manifest, "m") is manifest
    with pytest.raises(MalformedRunError, match=r"^m: jobs must be a non-empty list of \[task, episode, seed\], got 'x'; "
                                                r"repair the file or re-create the run"):
        check_manifest({**manifest, "jobs": "x"}, "m")
    row = json.loads((BASELINE / "results.jsonl").read_text().splitlines()[0])
    assert check_row(row, "r", 1, {("Lift", 0), ("Lift", 1)}) is row
    with pytest.raises(MalformedRunError, match=r"^r line 4: success must be true or false, got str 'yes'"):
        check_row({**row, "success": "yes"}, "r", 4)


def test_a_cut_short_episode_array_is_one_line_and_exit_2_in_compare(runs, tmp_path, capsys):
    """A damaged attention.npz (a full disk, a killed copy) must not read as a regression (exit 1)."""
    good, bad = runs
    path = bad / "Lift" / "episode_2" / "attention.npz"
    path.write_bytes(path.read_bytes()[:300])
    _one_line_exit_2(["compare", str(good), str(bad), "--out", str(tmp_path / "cmp")], capsys,
                     "episode_2/attention.npz is damaged (300 bytes, its row records")

"""The EVAL.md section generators write the provenance line themselves (issue 43 item 5): the command, the checkout's
commit and the machine from the runs' manifests, in the form tests/docs/test_provenance.py checks, so regenerating
a section keeps it."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from harness.analysis.provenance import PROVENANCE_LINE, machine_text, provenance_line, with_provenance

REPO = Path(__file__).resolve().parents[2]
XEON = {"machine": "x86_64", "cpu": {"model": "Intel(R) Xeon(R) Processor", "cores": 2}, "jax": {"backend": "cpu"}}
H100 = {"machine": "x86_64", "cpu": {"model": "AMD EPYC 9454", "cores": 16},
        "jax": {"backend": "gpu", "device_kind": "NVIDIA H100 80GB HBM3"}}


def test_the_machine_comes_from_the_manifests_platform():
    assert machine_text([XEON, XEON]) == "Intel(R) Xeon(R) Processor (x86_64), 2 cores, CPU only"
    assert machine_text([H100]) == "AMD EPYC 9454 (x86_64), 16 cores, GPU NVIDIA H100 80GB HBM3"
    mixed = machine_text([XEON, H100, H100, None])
    assert "Xeon(R) Processor (x86_64), 2 cores, CPU only (1 runs)" in mixed and "(2 runs)" in mixed
    assert "1 runs without a recorded platform" in mixed
    assert machine_text([None, {}]) == "not recorded in the runs' manifests"


def test_the_line_names_the_command_the_checkout_and_the_runs_commits():
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    line = provenance_line("bash scripts/x.sh a;b `c`", [{"platform": XEON, "git_commit": "0123456789abcdef"}])
    match = PROVENANCE_LINE.fullmatch(line)
    assert match and match.group(1) == "0123456789ab", line  # the commit that produced the figures: the runs'
    assert f"this section written at `{head[:12]}`" in line and "command `bash scripts/x.sh a,b 'c'`" in line
    several = provenance_line("x", [{"git_commit": "0123456789abcdef"}, {"git_commit": "fedcba9876543210"}])
    match = PROVENANCE_LINE.fullmatch(several)  # runs of several commits: the checkout's, naming each of theirs
    assert match and head.startswith(match.group(1)) and "the runs recorded `0123456789ab`, `fedcba987654`" in several
    assert line.endswith("machine: Intel(R) Xeon(R) Processor (x86_64), 2 cores, CPU only.")
    section = with_provenance("## Robustness\n\nnote\n\n| a |\n", line)
    assert section.startswith(f"## Robustness\n\n{line}\n\nnote\n")


def _run(folder: Path, task: str, outcomes) -> Path:
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text(json.dumps({"platform": XEON, "git_commit": None}))
    (folder / "results.jsonl").write_text("".join(
        json.dumps({"task": task, "episode": i, "status": "ok", "success": ok, "seed": i, "steps": 10,
                    "directory": f"{task}/episode_{i}"}) + "\n" for i, ok in enumerate(outcomes)))
    return folder


def test_the_evaluation_table_written_twice_keeps_one_provenance_line(tmp_path):
    from reference_policies.evaluate import main

    runs = [str(_run(tmp_path / "Lift", "Lift", [True, True, False])), str(_run(tmp_path / "Stack", "Stack", [False]))]
    out = tmp_path / "model"
    out.mkdir()
    (out / "EVAL.md").write_text("# old\n\n## Robustness\n\nkept\n")
    for _ in range(2):
        assert main([*runs, "--out", str(out), "--command", "bash scripts/evaluate_reference.sh"]) == 0
    text = (out / "EVAL.md").read_text()
    top, kept = text.split("\n## Robustness\n")
    assert len(PROVENANCE_LINE.findall(top)) == 1 and kept.strip() == "kept"
    line = PROVENANCE_LINE.search(top).group(0)
    assert "command `bash scripts/evaluate_reference.sh`" in line and "the runs recorded no commit" in line
    assert line.endswith("2 cores, CPU only.") and "| Lift | 3 | 2 |" in top
    # the figures file holds what the section is rendered from, its provenance line included: rendering it again
    # from eval.json alone (no runs) gives the same EVAL.md
    from reference_policies.evaluate import FIGURES, render, rerender

    data = json.loads((out / FIGURES).read_text())
    assert data["provenance"] == line and render(data).strip() == top.strip()
    rerender(out)
    assert (out / "EVAL.md").read_text() == text


def test_an_evaluation_is_written_only_into_the_checkpoint_its_runs_were_made_with(fixtures_dir, tmp_path, capsys):
    """A promoted checkpoint (the same files in another folder) takes its runs' evaluation; a checkpoint whose
    files differ from the runs' recorded fingerprint is refused in one line, EVAL.md untouched; so is a run folder
    whose manifest.json is not JSON."""
    import shutil

    import pytest

    from reference_policies.evaluate import main
    from harness.run.protocol import model_fingerprint

    run = _run(tmp_path / "run", "Lift", [True, False])
    fingerprint = model_fingerprint(str(fixtures_dir / "tiny"))[1]
    (run / "manifest.json").write_text(json.dumps({"platform": XEON, "git_commit": None,
                                                   "model": {"fingerprint": fingerprint}}))
    promoted = tmp_path / "promoted"
    shutil.copytree(fixtures_dir / "tiny", promoted)
    assert main([str(run), "--out", str(promoted)]) == 0 and "| Lift | 2 | 1 |" in (promoted / "EVAL.md").read_text()

    other = tmp_path / "other"
    shutil.copytree(fixtures_dir / "tiny", other)
    (other / "config.json").write_text((other / "config.json").read_text() + " ")
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        main([str(run), "--out", str(other)])
    assert exit_info.value.code == 2 and not (other / "EVAL.md").exists()
    (line,) = [text for text in capsys.readouterr().err.splitlines() if "error:" in text]
    assert "was made with another checkpoint" in line and "pass --out the folder the runs evaluated" in line

    (run / "manifest.json").write_text("{not json")
    with pytest.raises(SystemExit) as exit_info:
        main([str(run), "--out", str(promoted)])
    assert exit_info.value.code == 2 and "manifest.json is unreadable" in capsys.readouterr().err

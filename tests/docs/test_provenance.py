"""Every results section names the command, the project commit and the machine it was measured on (issue 43 item 5):
each section of models/*/EVAL.md, the measured sections of the model cards (models/*/README.md) and the docs/ sections
that quote measured figures (DOCS_MEASURED) hold one line
`Provenance: command `...`; commit `<hash>` ...; machine: ...`, and the commit exists in a git checkout."""

from __future__ import annotations

import subprocess
from pathlib import Path

from harness.analysis.provenance import PROVENANCE_LINE

REPO = Path(__file__).resolve().parents[2]
LINE = PROVENANCE_LINE  # the one definition, which the section generators' lines are tested against too
CARD_MEASURED = ("## What was measured", "## Evaluation")  # model-card sections that quote measured figures


def _sections(path: Path) -> list[tuple[str, str]]:
    """(heading, body) of the file's top section (its # title) and each ## section."""
    out, heading, body = [], None, []
    for line in path.read_text().splitlines():
        if line.startswith("# ") or line.startswith("## "):
            if heading is not None:
                out.append((heading, "\n".join(body)))
            heading, body = line, []
        else:
            body.append(line)
    if heading is not None:
        out.append((heading, "\n".join(body)))
    return out


# docs/ sections that quote measured figures (results on the reference policies, benchmark timings). Examples of a
# command's output on made-up inputs (regression.md's Outcomes and Drift) are not measurements and are not listed.
DOCS_MEASURED = (
    ("docs/benchmarks.md", "# Benchmarks"),
    ("docs/environments.md", "## Is the harness feeding the model what it was trained on?"),
    ("docs/faithfulness-sanity.md", "## Results on the reference policy"),
    ("docs/faithfulness.md", "## Results on the 4×4-grid reference policy"),
    ("docs/faithfulness.md", "## Results on the previous 8×8-grid policy"),
    ("docs/faithfulness.md", "## Cost"),
    ("docs/faithfulness.md", "## Results: reliance on the reference policy"),
    ("docs/libero-reference.md", "## Results"),
    ("docs/history/libero-reference.md", "## Results of the first recipe"),
    ("docs/libero.md", "## The scripted expert: the env path end to end"),
    ("docs/libero.md", "## Cost (benchmarks/bench_libero.py)"),
    ("docs/parallel.md", "## Throughput (benchmarks/bench_parallel.py)"),
    ("docs/parallel.md", "## Running on a GPU machine"),
    ("docs/perturbations.md", "## Cost"),
    ("docs/perturbations.md", "## Measured: the reference policy on the grid"),
    ("docs/perturbations.md", "## Measured: the wrist camera, with reliance"),
    ("docs/perturbations.md", "## Measured: the scene cells, with reliance"),
    ("docs/history/libero-reference.md", "## Grasp probe: what each lever changes"),
    ("docs/history/libero-reference.md", "## Swapped-instruction demonstrations: the grounding lever"),
    ("docs/history/libero-reference.md", "## The reference checkpoint"),
    ("docs/phases-and-position.md", "## Cost"),
    ("docs/phases-and-position.md", "## Reference policy: results"),
    ("docs/regression.md", "## Across machines: provenance, replay and what a verdict can claim"),
    ("docs/running.md", "## What a run costs"),
    ("docs/viewer.md", "## Cost (benchmarks/bench_rerun.py)"),
)


def _docs_sections() -> list[tuple[Path, str, str]]:
    found = []
    for name, heading in DOCS_MEASURED:
        bodies = [b for h, b in _sections(REPO / name) if h == heading]
        assert len(bodies) == 1, f"{name}: no single section {heading!r} (renamed? update DOCS_MEASURED)"
        found.append((REPO / name, heading, bodies[0]))
    return found


def _results_sections() -> list[tuple[Path, str, str]]:
    found = _docs_sections()
    for path in sorted(REPO.glob("models/*/EVAL.md")):
        found += [(path, h, b) for h, b in _sections(path)]
    for path in sorted(REPO.glob("models/*/README.md")):
        found += [(path, h, b) for h, b in _sections(path) if h.startswith(CARD_MEASURED)]
    return found


def test_every_results_section_has_a_provenance_line():
    sections = _results_sections()
    assert len(sections) >= 12 + len(DOCS_MEASURED)  # three EVAL.md files (9 sections), three model cards, docs
    missing = [f"{p.relative_to(REPO)}: {h}" for p, h, b in sections if len(LINE.findall(b)) != 1]
    assert not missing, "sections without exactly one provenance line:\n" + "\n".join(missing)


def test_provenance_commits_exist():
    if not (REPO / ".git").exists():
        return  # an exported tree: the format check above still runs
    for path, heading, body in _results_sections():
        commit = LINE.search(body).group(1)
        known = subprocess.run(["git", "-C", str(REPO), "cat-file", "-e", f"{commit}^{{commit}}"], capture_output=True)
        assert known.returncode == 0, f"{path.name} {heading}: commit {commit} is not in this repository"


def test_the_check_catches_a_section_without_one(tmp_path):
    page = tmp_path / "EVAL.md"
    page.write_text("# m: evaluation\n\nProvenance: command `bash x.sh`; commit `abcdef1`; machine: a CPU.\n\n## Robustness\n\n"
                    "| a | 1 |\n")
    bodies = dict(_sections(page))
    assert len(LINE.findall(bodies["# m: evaluation"])) == 1 and not LINE.findall(bodies["## Robustness"])

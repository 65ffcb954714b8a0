"""Claims of the docs that the code decides (issue 71 item 5): what a hung LIBERO server costs an episode, what a
grid cell that loses more than `--max-drop` is, and which jax version the GPU figures were measured on. Each claim is
read from the pages and held to the code or to pyproject.toml; no simulator runs."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from tests.docs.test_docs import doc_files, prose_lines

REPO = Path(__file__).resolve().parents[2]


def paragraphs(path: Path) -> list[str]:
    """A page's prose paragraphs and list items, each on one line."""
    text = "\n".join(prose_lines(path.read_text()))
    blocks = re.split(r"\n\s*\n|\n(?=\s*[-*] )|\n(?=\|)", text)
    return [" ".join(b.split()) for b in blocks if b.strip()]


def pages() -> list[Path]:
    return [p for p in [*doc_files(), REPO / "CHANGELOG.md"] if "history" not in p.parts]


HUNG = re.compile(r"LIBERO (server|simulator)\b.*\b(does not answer|did not answer|hung)|\bhung\b.*LIBERO", re.I)


def hung_server_claims() -> list[tuple[str, str]]:
    return [(p.name, para) for p in pages() for para in paragraphs(p) if HUNG.search(para)]


def test_a_hung_libero_server_is_said_to_be_retried_as_the_code_does():
    """A server that does not answer raises LiberoServerLost, an infrastructure failure (harness.run.executor.
    failure_of, asserted on the real timeout in tests/libero/test_libero_env.py): retried, never 'fails its
    episode'."""
    claims = hung_server_claims()
    assert {"libero.md", "CHANGELOG.md"} <= {page for page, _ in claims}, claims
    for page, para in claims:
        assert re.search(r"retried|retries|infrastructure", para), (page, para)
        assert not re.search(r"fails its episode|episode is recorded as failed", para), (page, para)


def gating_on_conditions() -> str:
    text = (REPO / "docs/perturbations.md").read_text()
    return " ".join(text.split("### Gating on conditions", 1)[1].split("\n## ", 1)[0].split())


def test_a_cell_that_loses_more_than_max_drop_is_named_with_every_verdict_it_can_get():
    """The verdicts of every table of up to 8 pairs whose loss is beyond --max-drop (harness.analysis.paired.decide,
    as compare decides a grid's cell): the section names each, and says which exit 0 (tests/gate/test_grid_gate.py
    runs such a grid)."""
    from harness.verdicts import gate_exit_code
    from harness.analysis.paired import PairedCounts, decide

    reachable = set()
    for n in range(1, 9):
        for both in range(n + 1):
            for lost in range(n - both + 1):
                for gained in range(n - both - lost + 1):
                    counts = PairedCounts(both, lost, gained, n - both - lost - gained)
                    if counts.difference < -0.1:
                        reachable.add(decide(counts, max_drop=0.1, alpha=0.05))
    assert reachable == {"REGRESSED", "SUSPECT", "UNDERPOWERED"}
    section = gating_on_conditions()
    for verdict in reachable:
        assert verdict in section, verdict
        if gate_exit_code(verdict) == 0:
            assert f"{verdict} (exit 0" in section, verdict


def _allowed_jax() -> tuple[str, str]:
    """pyproject.toml's jax range, as (lowest allowed, first excluded), for the package and the [cuda] extra."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    specs = [d for d in project["dependencies"] if re.match(r"jax\b", d)]
    specs += [d for d in project["optional-dependencies"]["cuda"] if d.startswith("jax")]
    ranges = {re.search(r">=([\d.]+),<([\d.]+)", d).groups() for d in specs}
    assert len(ranges) == 1, specs  # the extra pins the package's range
    return ranges.pop()


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(x) for x in text.split("."))


def sections(path: Path) -> list[str]:
    """A page's "## " sections, each on one line."""
    text = "\n".join(prose_lines(path.read_text()))
    return [" ".join(part.split()) for part in re.split(r"\n(?=## )", text)]


def test_gpu_figures_say_the_jax_version_they_were_measured_on_and_that_it_is_outside_the_range():
    """A section that gives figures on a jax version pyproject.toml does not allow says so: the allowed range as
    pyproject.toml has it (the package's and the [cuda] extra's), and that the figures were not re-measured on it."""
    low, high = _allowed_jax()
    outside = []
    for page in pages():
        for section in sections(page):
            for version in re.findall(r"\bjax (\d+\.\d+(?:\.\d+)?)\b", section):
                if not _version(low) <= _version(version) < _version(high):
                    outside.append((page.name, version, section))
    assert outside, "no page gives figures measured outside the allowed jax range: drop this test's premise"
    for page, version, section in outside:
        assert f"`>={low},<{high}`" in section and "`[cuda]` extra" in section, (page, version, section[:300])
        assert re.search(rf"{re.escape(version)} is outside that range.*not re-measured", section), (page, version)


def test_the_docs_say_that_fail_on_changed_gates_a_grid_as_suspect():
    """harness.gate.regress.grid_fail_on, whose line tests/gate/test_grid_gate.py checks on stderr."""
    for page in ("regression.md", "perturbations.md"):
        said = [p for p in paragraphs(REPO / "docs" / page)
                if "grid" in p and "`--fail-on changed` gates" in p and "as `--fail-on suspect`" in p]
        assert said and "one line" in said[0], page

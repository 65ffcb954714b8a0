"""The README answers a newcomer's five questions in its first 100 lines, each with a command that runs as written
(issue 67): set-up, running one's own checkpoint, where the outputs land, comparing two checkpoints, gating in CI.

The commands are read from the README's bash blocks and run on the tiny reference fixture, with these substitutions
only: every model becomes the fixture, `--task` becomes Lift, `--episodes` 1, a run gets `--max-steps 1`, and
`results/` becomes a temporary folder; the second run of the comparison writes no PNG or MP4 (output options may
differ between compared runs). The output tree the README draws is checked against the run folder the quick
start made. The CI command is the script tests/docs/test_ci_recipe.py runs; here it is checked to be that script, with
settings of its own prefix only, gating a checkpoint against another version of it (issue 71 item 4).
"""

from __future__ import annotations

import hashlib
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
FIRST_LINES = 100

pytestmark = pytest.mark.slow


def front_commands() -> list[list[str]]:
    """The commands of the bash blocks in the README's first lines, as argument lists (comments dropped)."""
    head = "\n".join((REPO / "README.md").read_text().splitlines()[:FIRST_LINES])
    blocks = re.findall(r"^```bash\n(.*?)^```", head, re.S | re.M)
    text = "\n".join(blocks).replace("\\\n", " ")
    return [shlex.split(line, comments=True) for line in text.splitlines() if line.strip()]


def find(commands: list[list[str]], *start: str) -> list[list[str]]:
    return [c for c in commands if c[: len(start)] == list(start)]


def assignments(argv: list[str]) -> tuple[dict[str, str], list[str]]:
    """A command's leading NAME=value environment settings, and the command after them."""
    n = next((i for i, arg in enumerate(argv) if not re.match(r"^[A-Za-z_]\w*=", arg)), len(argv))
    return dict(arg.split("=", 1) for arg in argv[:n]), argv[n:]


def ci_commands(commands: list[list[str]]) -> list[tuple[dict[str, str], list[str]]]:
    return [(env, rest) for env, rest in map(assignments, commands) if rest[:2] == ["bash", "examples/ci/regress-gate.sh"]]


def on_fixture(argv: list[str], tiny: Path, tmp: Path) -> list[str]:
    """The README's command with the substitutions named above."""
    out, skip = [], False
    for i, arg in enumerate(argv):
        if skip:
            skip = False
            continue
        if arg in ("--model", "--task", "--episodes") and i + 1 < len(argv):
            out += [arg, {"--model": str(tiny), "--task": "Lift", "--episodes": "1"}[arg]]
            skip = True
        else:
            out.append(re.sub(r"^results/", f"{tmp}/", arg))
    if out[:2] == [".venv/bin/octo-harness", "run"]:
        out += ["--max-steps", "1", "--out", str(tmp / "runs")]
        if "other" in argv:  # the comparison's second run: its arrays are what compare and report read
            out += ["--png-every", "0", "--no-video"]
    if out[0] == ".venv/bin/octo-harness":
        harness = Path(sys.executable).with_name("octo-harness")
        out[0] = str(harness) if harness.exists() else "octo-harness"
    return out


def run_entry_point(argv: list[str]) -> subprocess.CompletedProcess:
    """An `octo-harness ...` command through the function its console script calls (pyproject.toml's
    [project.scripts]: harness.cli:main), in this process: the same command without a second interpreter's start-up
    (imports, JAX; about a third of each command's time here). tests/docs/test_ci_recipe.py runs the console script
    itself."""
    import contextlib
    import io
    import tomllib

    from harness import cli

    assert tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]["octo-harness"] == "harness.cli:main"
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(argv[1:])
    assert code == 0, f"{shlex.join(argv)}: exit {code}\n{out.getvalue()[-2000:]}{err.getvalue()[-2000:]}"
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())


def run(argv: list[str]) -> subprocess.CompletedProcess:
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    done = subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"{shlex.join(argv)}: exit {done.returncode}\n{done.stdout[-2000:]}{done.stderr[-2000:]}"
    return done


def test_the_first_lines_hold_a_command_for_each_question():
    commands = front_commands()
    assert find(commands, "bash", "scripts/demo.sh") and find(commands, "bash", "scripts/test.sh")  # set-up
    runs = find(commands, ".venv/bin/octo-harness", "run")
    assert any("--run-name" in c and "--model" in c for c in runs)  # one's own checkpoint, into a named run
    assert find(commands, ".venv/bin/octo-harness", "compare")  # two checkpoints
    assert find(commands, ".venv/bin/octo-harness", "report")
    assert ci_commands(commands)  # CI
    head = "\n".join((REPO / "README.md").read_text().splitlines()[:FIRST_LINES])
    assert re.search(r"^results/runs/\w+/$", head, re.M), "the output tree of a run"


def test_the_ci_command_is_the_tested_script():
    """One candidate, a model of this repository, gated against the version of it at OCTO_GATE_BASE_REV: another
    checkpoint at the same path (the pull request's case), not the candidate itself. Settings have the script's prefix."""
    ((env, ci),) = ci_commands(front_commands())
    assert len(ci) == 3 and (REPO / ci[2] / "config.json").is_file(), ci
    assert env and all(name.startswith("OCTO_GATE_") for name in env), env
    assert set(env) <= set(re.findall(r"\b(OCTO_GATE_[A-Z_]+)=", (REPO / ci[1]).read_text())), env  # its settings
    rev = env["OCTO_GATE_BASE_REV"]

    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True)

    if git("rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}").returncode != 0:
        pytest.skip(f"{rev} is not in this clone's history (a shallow clone?): its checkpoint cannot be compared")

    def weights(revision: str) -> str:  # the checkpoint's configuration and step folders, as git records them
        listing = git("ls-tree", "-r", revision, "--", f"{ci[2]}/").stdout.splitlines()
        return "\n".join(l for l in listing if re.search(r"/(\d+/|config\.json$)", l.split("\t")[1]))

    base, head = weights(rev), weights("HEAD")
    assert base and head and base != head, f"{ci[2]} at {rev} is the same checkpoint as at HEAD: the example gates it against itself"


@pytest.fixture(scope="module")
def front_page_runs(fixtures_dir, tmp_path_factory):
    """The set-up's demo, the quick start and the comparison, run in the README's order on the fixture."""
    tmp = tmp_path_factory.mktemp("readme")
    tiny = fixtures_dir / "tiny"
    commands = front_commands()
    stamp = REPO / ".venv" / (".installed-" + hashlib.sha1((REPO / "pyproject.toml").read_bytes()).hexdigest()[:12])
    assert stamp.is_file(), ("scripts/demo.sh would install .venv first (its stamp for this pyproject.toml is missing): "
                             "run bash scripts/test.sh, which installs it, before the docs tests")
    (demo,) = find(commands, "bash", "scripts/demo.sh")
    done = {"demo": run([*demo, "--model", str(tiny), "--max-steps", "1", "--png-every", "0", "--no-video",
                         "--out", str(tmp / "demo")])}
    named = [c for c in find(commands, ".venv/bin/octo-harness", "run") if "--run-name" in c]
    for argv in [*named, *find(commands, ".venv/bin/octo-harness", "compare"),
                 *find(commands, ".venv/bin/octo-harness", "report")]:
        done[shlex.join(argv[1:3])] = run_entry_point(on_fixture(argv, tiny, tmp))
    return tmp, done


def test_the_set_up_demo_runs(front_page_runs):
    tmp, done = front_page_runs
    assert "results:" in done["demo"].stdout
    assert list((tmp / "demo").glob("*/results.jsonl"))


def test_the_quick_start_writes_the_tree_the_readme_draws(front_page_runs):
    tmp, _ = front_page_runs
    text = (REPO / "README.md").read_text().splitlines()[:FIRST_LINES]
    top = next(i for i, line in enumerate(text) if re.match(r"^results/runs/\w+/$", line))
    run_dir = tmp / "runs" / text[top].split("/")[2]
    drawn, folder = [], run_dir
    for line in text[top + 1:]:
        if line.startswith("```"):
            break
        name = line.split()[0]
        if name.endswith("/"):
            folder = run_dir / name
        else:
            drawn.append(folder / name)
    assert len(drawn) >= 8
    assert [str(p.relative_to(run_dir)) for p in drawn if not p.is_file()] == []


def test_the_comparison_writes_its_verdict_and_report(front_page_runs):
    tmp, done = front_page_runs
    assert "octo-harness compare: IDENTICAL" in done["compare results/runs/mine"].stdout  # the same fixture twice
    (report,) = find(front_commands(), ".venv/bin/octo-harness", "report")
    out = Path(on_fixture(report, Path("unused"), tmp)[report.index("--out") + 1])
    assert (out / "report.html").is_file() and (out / "tables" / "success.csv").is_file()

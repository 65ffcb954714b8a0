"""The documentation stays true: README.md is a front page (at most 160 lines), every relative link and #anchor in
README.md and docs/*.md resolves, every option of every command's --help is documented, every docs page is in the
index, and the Python API page's examples run.

Anchors are computed as GitHub computes them from headings: the heading's text (markup removed) lowercased, every
character that is not a letter, digit, underscore, hyphen or space dropped, spaces turned into hyphens, and a
repeated anchor suffixed -1, -2, ... in order of appearance.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
README_MAX_LINES = 160  # a front page (issue 67): pitch, set-up, quick start, recipes, findings, docs


def doc_files(root: Path = REPO) -> list[Path]:
    """README.md and every Markdown page under docs/ (whatever other work adds there)."""
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


# ---- a small Markdown reader: fenced code, headings, links ------------------------------------------------------

FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})")
ATX = re.compile(r"^ {0,3}(#{1,6})(?:[ \t]+(.*?))?(?:[ \t]+#+)?[ \t]*$")
SETEXT = re.compile(r"^ {0,3}(=+|-+)[ \t]*$")
INLINE_CODE = re.compile(r"(`+)(.+?)\1", re.S)
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE = re.compile(r"^ {0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s.*)?$", re.M)
HTML_ATTR = re.compile(r"""<(?:a|img|source|video)\b[^>]*?\b(?:href|src)\s*=\s*["']([^"']+)["']""", re.I)
HTML_ID = re.compile(r"""<[a-z]+\b[^>]*?\b(?:id|name)\s*=\s*["']([^"']+)["']""", re.I)


def prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks (fenced lines become empty, so line numbers keep)."""
    lines, fence = [], None
    for line in text.splitlines():
        m = FENCE.match(line)
        if fence is None and m:
            fence = m.group(1)
            lines.append("")
        elif fence is not None:
            if m and m.group(1)[0] == fence[0] and len(m.group(1)) >= len(fence) and not line.strip()[len(m.group(1)):].strip():
                fence = None
            lines.append("")
        else:
            lines.append(line)
    return lines


def heading_texts(text: str) -> list[str]:
    """The headings' source text (ATX `# ...` and setext underlined ones) outside fenced code, in order."""
    lines = prose_lines(text)
    out = []
    for i, line in enumerate(lines):
        m = ATX.match(line)
        if m:
            out.append(m.group(2) or "")
            continue
        previous = lines[i - 1] if i else ""
        if SETEXT.match(line) and previous.strip() and not ATX.match(previous) and not previous.lstrip().startswith(("|", ">", "-", "*", "+")) \
                and (i < 2 or not lines[i - 2].strip()):
            out.append(previous.strip())
    return out


def slug(heading: str) -> str:
    """GitHub's anchor of one heading (before de-duplication)."""
    text = INLINE_CODE.sub(lambda m: m.group(2), heading)
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)  # links and images: their text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML tags
    text = re.sub(r"(\*{1,3}|(?<!\w)_{1,3}|_{1,3}(?!\w))", "", text)  # emphasis markers (not underscores inside words)
    text = text.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(text: str) -> set[str]:
    """Every anchor a page defines: its headings' slugs, de-duplicated as GitHub does, and explicit HTML ids."""
    seen: dict[str, int] = {}
    out = set()
    for heading in heading_texts(text):
        base = slug(heading)
        if base in seen:
            seen[base] += 1
            candidate = f"{base}-{seen[base]}"
            while candidate in seen:  # "a", "a", "a-1" -> a, a-1, a-1-1 (GitHub's rule)
                seen[base] += 1
                candidate = f"{base}-{seen[base]}"
            seen[candidate] = 0
            out.add(candidate)
        else:
            seen[base] = 0
            out.add(base)
    out |= set(HTML_ID.findall("\n".join(prose_lines(text))))
    return out


def link_targets(text: str) -> list[str]:
    """Link and image targets in prose (not in code blocks or code spans)."""
    prose = INLINE_CODE.sub("", "\n".join(prose_lines(text)))
    return [*LINK.findall(prose), *REFERENCE.findall(prose), *HTML_ATTR.findall(prose)]


def broken_links(page: Path, root: Path) -> list[str]:
    """Relative links of `page` whose file is missing, that leave `root`, or whose #anchor no heading defines."""
    problems = []
    for target in link_targets(page.read_text()):
        if not target or re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:, ...
            continue
        path_part, _, anchor = target.partition("#")
        from urllib.parse import unquote

        path_part = unquote(path_part)
        if path_part.startswith("/"):
            problems.append(f"{target}: absolute path; link relative to the page")
            continue
        resolved = (page.parent / path_part).resolve() if path_part else page.resolve()
        if resolved != root.resolve() and root.resolve() not in resolved.parents:
            problems.append(f"{target}: leaves the repository")
            continue
        if not resolved.exists():
            problems.append(f"{target}: {resolved.relative_to(root.resolve())} does not exist")
            continue
        if anchor:
            if resolved.is_dir() or resolved.suffix.lower() != ".md":
                problems.append(f"{target}: an anchor into a file that is not Markdown")
            elif unquote(anchor) not in anchors(resolved.read_text()):
                problems.append(f"{target}: no heading of {resolved.relative_to(root.resolve())} has anchor #{anchor}")
    return problems


# ---- the checks on this repository ------------------------------------------------------------------------------

def test_readme_is_a_front_page():
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; move detail into docs/ (at most {README_MAX_LINES})"
    text = "\n".join(lines)
    assert "bash scripts/demo.sh" in text and "bash scripts/test.sh" in text
    assert re.search(r"!\[[^\]]*\]\(docs/[^)]+\.png\)", text), "the front page shows one picture from docs/"


@pytest.mark.parametrize("page", doc_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_and_anchor_resolves(page):
    assert broken_links(page, REPO) == []


def cli_options(parser: argparse.ArgumentParser, command: str = "octo-harness") -> dict[str, set[str]]:
    """{long option: the commands that take it}, walking the subcommands' parsers (top-level options included)."""
    found: dict[str, set[str]] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                for option, commands in cli_options(sub, f"{command} {name}").items():
                    found.setdefault(option, set()).update(commands)
            continue
        for option in action.option_strings:
            if option.startswith("--") and option != "--help":
                found.setdefault(option, set()).add(command)
    return found


def documented(option: str, text: str) -> bool:
    return re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text) is not None


def test_every_option_of_every_command_is_documented():
    from harness.cli import build_parser

    options = cli_options(build_parser())
    assert {"--debug", "--verbose", "--png-every", "--fail-on", "--bins", "--action-tolerance"} <= set(options)
    text = "\n".join(p.read_text() for p in doc_files())
    missing = sorted(f"{o} ({', '.join(sorted(options[o]))})" for o in options if not documented(o, text))
    assert missing == [], "document these options in README.md or a docs/ page: " + "; ".join(missing)


def test_every_docs_page_is_in_the_index():
    index = REPO / "docs" / "README.md"
    linked = {(index.parent / t.partition("#")[0]).resolve() for t in link_targets(index.read_text()) if t.partition("#")[0]}
    pages = [p for p in doc_files()[1:] if p != index]
    assert [str(p.relative_to(REPO)) for p in pages if p.resolve() not in linked] == []


def test_the_exit_codes_of_run_are_documented():
    running = (REPO / "docs" / "running.md").read_text()
    assert "exit-codes" in anchors(running)
    section = running.split("## Exit codes", 1)[1].split("\n## ", 1)[0]
    for code in (0, 1, 2, 130, 143):
        assert re.search(rf"^\| \*\*{code}\*\* \|", section, re.M), f"exit code {code} of run is not in the table"


REPO_PATH = re.compile(r"(?<![\w/.-])((?:harness|envs|tests|benchmarks|scripts|models|docs|\.ci)/[\w./-]*\w)")
DOTTED = re.compile(r"(?<![\w/.-])((?:harness|envs)(?:\.\w+)+)")


def stale_names(text: str, root: Path = REPO) -> list[str]:
    """Repository paths (`harness/runfolder/schema.py`, `scripts/demo.sh`) and dotted names (`harness.run.execute`,
    `envs.make`) a page mentions that no longer exist: a path that is missing, or a name whose longest module
    prefix does not exist or does not mention the next part. Placeholders (`<run>`, `*.png`) are skipped."""
    stale = []
    for path in REPO_PATH.findall(text):
        if "<" not in path and "*" not in path and not (root / path).exists():
            stale.append(path)
    for dotted in DOTTED.findall(text):
        if dotted == "harness.toml":  # a checkpoint's file, not a module
            continue
        parts = dotted.split(".")
        for n in range(len(parts), 0, -1):
            base = root.joinpath(*parts[:n])
            module = next((f for f in (base.with_suffix(".py"), base / "__init__.py") if f.is_file()), None)
            if module is not None:
                if parts[n:] and not re.search(rf"\b{re.escape(parts[n])}\b", module.read_text()):
                    stale.append(dotted)
                break
        else:
            stale.append(dotted)
    return sorted(set(stale))


@pytest.mark.parametrize("page", doc_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_the_files_and_modules_a_page_names_exist(page):
    assert stale_names(page.read_text()) == []


# ---- the checker itself, on hand-made pages (each can fail) -----------------------------------------------------

def test_anchors_follow_github(tmp_path):
    text = ("# Set-up (fresh Debian/Ubuntu machine, two commands)\n## Throughput (benchmarks/bench_parallel.py)\n"
            "## Results on the 4×4-grid `policy`\n## A checkpoint's conventions (`harness.toml`)\n"
            "## Notes\n## Notes\n## Notes\n```\n## not a heading\n```\nSetext heading\n--------------\n"
            "### **Bold** and [a link](x.md)\n")
    assert anchors(text) == {
        "set-up-fresh-debianubuntu-machine-two-commands", "throughput-benchmarksbench_parallelpy",
        "results-on-the-44-grid-policy", "a-checkpoints-conventions-harnesstoml", "notes", "notes-1", "notes-2",
        "setext-heading", "bold-and-a-link"}


def test_broken_links_are_found(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text("# A page\n\n## Exit codes\n")
    (tmp_path / "pic.png").write_bytes(b"")
    page = tmp_path / "README.md"
    page.write_text(
        "# Front\n[ok](docs/a.md) [ok anchor](docs/a.md#exit-codes) [self](#front) ![pic](pic.png)\n"
        "[web](https://example.org/x#y) `[not a link](nowhere.md)`\n"
        "```\n[in code](nowhere.md)\n```\n"
        "[missing](docs/b.md) [bad anchor](docs/a.md#exit-code) [bad self](#back) [outside](../elsewhere.md)\n"
        "[anchor in a picture](pic.png#x) [absolute](/etc/passwd)\n[ref]: docs/c.md\n")
    problems = broken_links(page, tmp_path)
    assert [p.split(":")[0] for p in problems] == [
        "docs/b.md", "docs/a.md#exit-code", "#back", "../elsewhere.md", "pic.png#x", "/etc/passwd", "docs/c.md"]


def test_an_option_is_found_only_whole():
    assert documented("--out", "use `--out DIR`") and documented("--out", "--out=DIR")
    assert not documented("--out", "see --outputs") and not documented("--seed", "--seeds 3")
    parser = argparse.ArgumentParser()
    parser.add_argument("--top")
    sub = parser.add_subparsers().add_parser("go")
    sub.add_argument("--deep", action="store_true")
    sub.add_argument("positional")
    assert cli_options(parser) == {"--top": {"octo-harness"}, "--deep": {"octo-harness go"}}


# ---- the Python API page runs -----------------------------------------------------------------------------------

@pytest.mark.slow
def test_the_python_api_examples_run(tmp_path):
    """Every ```python block of docs/python-api.md, in order, in one interpreter (a notebook), from a folder holding
    the repository's models/ (the run goes to tmp_path/results/runs)."""
    (tmp_path / "models").symlink_to(REPO / "models")
    blocks = re.findall(r"^```python\n(.*?)^```", (REPO / "docs" / "python-api.md").read_text(), re.S | re.M)
    assert len(blocks) >= 5
    script = tmp_path / "notebook.py"
    script.write_text("\n".join(f"# ---- block {i}\n{b}" for i, b in enumerate(blocks)))
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}  # as in a notebook
    env.update(PYTHONPATH=str(REPO), HF_HUB_OFFLINE="1")
    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "complete results/runs/notebook-lift" in done.stdout
    assert (tmp_path / "results" / "runs" / "notebook-lift" / "results.jsonl").is_file()
    assert "(8, 8)" in done.stdout  # the camera map of the reference policy's primary camera


def test_stale_names_are_found():
    text = ("`harness/runfolder/schema.py`, `scripts/demo.sh`, `results/runs/<run>`, `docs/*.png`, `harness.run.execute`, "
            "`envs.make`, `harness.toml`, `harness/run/gone.py`, `harness.run.gone`, `harness.nowhere.thing`, "
            "`envs.no_such_function`")
    assert stale_names(text) == ["envs.no_such_function", "harness.nowhere.thing", "harness.run.gone",
                                 "harness/run/gone.py"]


# ---- a page that sends an option elsewhere sends it where it is documented ---------------------------------------

POINTER = re.compile(r"([^;.:]*):\s*\[[^\]]*\]\(([^)\s]+)\)")  # "... `--flag` ...: [page](target)"


def section_of(text: str, anchor: str) -> str:
    """The lines of the section (to the next heading of its level or above) whose heading has `anchor`; the whole
    page without one."""
    if not anchor:
        return text
    lines = text.splitlines()
    for i, line in enumerate(lines):
        m = ATX.match(line)
        if m and slug(m.group(2) or "") == anchor:
            end = next((j for j in range(i + 1, len(lines)) if (n := ATX.match(lines[j])) and
                        len(n.group(1)) <= len(m.group(1))), len(lines))
            return "\n".join(lines[i:end])
    return ""


def misdirected_options(page: Path) -> list[str]:
    """`--flag: [page](target)` pointers of `page` whose target (the section, with an anchor) never names the flag."""
    wrong = []
    for line in prose_lines(page.read_text()):
        for before, target in POINTER.findall(line):
            path_part, _, anchor = target.partition("#")
            if re.match(r"^[a-z][a-z0-9+.-]*:", target) or not path_part.endswith(".md"):
                continue
            where = (page.parent / path_part).resolve()
            text = section_of(where.read_text(), anchor) if where.is_file() else ""
            wrong += [f"{flag} -> {target}" for flag in re.findall(r"`(--[\w-]+)", before) if not documented(flag, text)]
    return wrong


@pytest.mark.parametrize("page", doc_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_an_option_sent_to_another_page_is_documented_there(page):
    assert misdirected_options(page) == []


def test_a_pointer_to_a_page_without_the_option_is_found(tmp_path):
    (tmp_path / "a.md").write_text("# A\n\n## GPU\n\n`--render-device cpu` renders on the CPU.\n\n## Other\n\nNone.\n")
    page = tmp_path / "b.md"
    page.write_text("Where it runs (`--workers`): [a.md](a.md); `--render-device`: [a.md](a.md#gpu).\n"
                    "`--render-device`: [a.md](a.md#other); see [a.md](a.md).\n")
    assert misdirected_options(page) == ["--workers -> a.md", "--render-device -> a.md#other"]

"""Every exit-code summary in the docs holds the exit codes the code returns (issue 71 item 5.4): the inline
summaries ("Exit codes: **0** pass, ..."), the tables of codes by command, and the `exit` column of the verdict
tables, each checked against the gate codes (harness.verdicts: each verdict's exit code, --fail-on's choices), the
replay's, the command line's internal error and the interrupts."""

from __future__ import annotations

import re
import signal
from pathlib import Path
from types import SimpleNamespace

import pytest

from harness.cli import INTERNAL_ERROR
from harness.gate.replay import exit_code as replay_exit_code
from harness.verdicts import DEFAULT_FAIL_ON, EXIT_FAIL, EXIT_INVALID, FAIL_ON, GateVerdict, ReplayVerdict, gate_exit_code
from tests.docs.test_docs import doc_files, prose_lines

INTERRUPTED = {128 + signal.SIGINT, 128 + signal.SIGTERM}
VERDICTS = {str(v): v for v in GateVerdict}
GATE = {gate_exit_code(v, f) for v in VERDICTS.values() for f in FAIL_ON} | {EXIT_INVALID, INTERNAL_ERROR}
REPLAY = {replay_exit_code(SimpleNamespace(verdict=v)) for v in ReplayVerdict} | {EXIT_INVALID, INTERNAL_ERROR}
# run: 1 when an episode failed (harness/cli/run.py), robustness: 1 when a run did not complete (cli/robustness.py)
OTHERS = {0, 1, EXIT_INVALID, INTERNAL_ERROR}
EXPECTED = {"compare": GATE, "regress": GATE, "replay": REPLAY, "run": OTHERS, "octo-harness run": OTHERS,
            "report": OTHERS, "view": OTHERS, "robustness": OTHERS, "sanity": OTHERS, "diagnose": OTHERS}

SUMMARY = re.compile(r"[Ee]xit codes\b[^:(.|\[\]]{0,60}?([:(])(?=\s*\*{0,2}\d)")  # ... a list that starts with a code
ITEM = re.compile(r"^\*{0,2}(\d+)\*{0,2}\s+(.*)$")


def inline_summaries(text: str) -> list[str]:
    """The text of each "Exit codes: ..." (to the sentence's end) or "Exit codes ... (...)" (to the parenthesis that
    closes it), in prose, lines joined."""
    prose = " ".join(" ".join(prose_lines(text)).split())
    found = []
    for m in SUMMARY.finditer(prose):
        rest = prose[m.end():]
        if m.group(1) == ":":
            found.append(re.split(r"\.(?:\s|$)", rest, maxsplit=1)[0])
        else:
            depth = 1
            for i, ch in enumerate(rest):
                depth += {"(": 1, ")": -1}.get(ch, 0)
                if depth == 0:
                    found.append(rest[:i])
                    break
    return found


def summary_codes(summary: str) -> dict[int, str]:
    """{code: its words} of a summary's comma-separated items that start with a code."""
    items = (ITEM.match(part.strip()) for part in re.split(r",\s*(?:or\s+)?", summary))
    return {int(m.group(1)): m.group(2) for m in items if m}


def check_words(code: int, words: str) -> list[str]:
    """The verdicts named in `words` whose exit code (at the default --fail-on) is not `code`."""
    return [v for v in re.findall(r"\b[A-Z]{4,}\b", words) if v in VERDICTS and gate_exit_code(VERDICTS[v]) != code]


def tables(text: str) -> list[list[list[str]]]:
    """The Markdown tables of a page's prose, as rows of cells (the separator row left out)."""
    out, rows = [], []
    for line in [*prose_lines(text), ""]:
        if line.startswith("|"):
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]]
            if not all(re.fullmatch(r":?-+:?", c) for c in cells):
                rows.append(cells)
        elif rows:
            out.append(rows)
            rows = []
    return out


def codes_of(cell: str) -> set[int]:
    """'**130 / 143**' -> {130, 143}; '**2**' -> {2}; 'other' -> set()."""
    return {int(n) for n in re.findall(r"\d+", cell)} if re.fullmatch(r"[*\d /]+", cell) else set()


def commands_of(cell: str) -> list[str]:
    return [c for c in re.findall(r"`([^`]+)`", cell) if c in EXPECTED]


def code_tables(text: str) -> dict[str, set[int]]:
    """{command: the codes its cells fill} of every table of exit codes by command: codes down the first column
    (header `code`) or across the header (`| command | 0 | 1 | ...`). An empty or '—' cell is a code it lacks."""
    found: dict[str, set[int]] = {}
    for rows in tables(text):
        header, body = rows[0], rows[1:]
        if header[0] == "code":
            for column, name in enumerate(header[1:], 1):
                for command in commands_of(name):
                    found.setdefault(command, set()).update(
                        c for row in body if row[column] not in ("", "—") for c in codes_of(row[0]))
        elif header[0] == "command" and codes_of(header[1]):
            for row in body:
                for command in commands_of(row[0]):
                    found.setdefault(command, set()).update(
                        c for column, cell in enumerate(row[1:], 1) if cell not in ("", "—")
                        for c in codes_of(header[column]))
    return found


def verdict_exit_rows(text: str) -> list[tuple[str, str]]:
    """(verdict, exit cell) of every table whose header is `verdict | ... | exit`."""
    return [(row[0], row[-1]) for rows in tables(text) if rows[0][0] == "verdict" and rows[0][-1] == "exit"
            for row in rows[1:]]


def pages() -> list[Path]:
    return [p for p in doc_files() if "history" not in p.parts]


def test_every_inline_summary_names_every_gate_code_with_its_meaning():
    summaries = [(p.name, s) for p in pages() for s in inline_summaries(p.read_text())]
    assert len(summaries) >= 2
    for page, summary in summaries:
        codes = summary_codes(summary)
        assert set(codes) - INTERRUPTED == GATE, (page, summary)
        assert all(check_words(code, words) == [] for code, words in codes.items()), (page, summary)
        assert "internal" in codes[INTERNAL_ERROR] and "invalid" in codes[EXIT_INVALID], (page, summary)


def test_every_table_of_codes_by_command_holds_the_codes_the_command_returns():
    seen = {}
    for page in pages():
        for command, codes in code_tables(page.read_text()).items():
            assert codes == EXPECTED[command] | INTERRUPTED, (page.name, command, sorted(codes))
            seen.setdefault(command, []).append(page.name)
    assert {"compare", "regress", "replay", "octo-harness run"} <= set(seen), seen


def test_the_exit_column_of_a_verdict_table_is_the_codes():
    rows = [row for page in pages() for row in verdict_exit_rows(page.read_text())]
    assert {v for v, _ in rows} == set(VERDICTS)  # regression.md's Outcomes and the glossary's gate verdicts
    for verdict, cell in rows:
        assert int(re.match(r"\d+", cell).group()) == gate_exit_code(VERDICTS[verdict]), (verdict, cell)
        for fail_on, code in re.findall(r"`--fail-on (\w+)`: (\d+)", cell):
            assert gate_exit_code(VERDICTS[verdict], fail_on) == int(code), (verdict, cell)


def test_the_checks_see_a_missing_or_wrong_code():
    text = ("Exit codes: **0** pass, **1** REGRESSED or SUSPECT, **2** invalid input (one line), **3** ERRORED.\n\n"
            "Exit codes are as for `compare` (0 pass, 1 ERRORED, 2 invalid input).\n\n"
            "| code | `compare` | `replay` |\n|---:|---|---|\n| **0** | pass | EQUIVALENT |\n| **1** | REGRESSED | — |\n\n"
            "| verdict | rule | exit |\n|---|---|---|\n| SUSPECT | x | 1 (`--fail-on regressed`: 1) |\n")
    first, second = inline_summaries(text)
    assert set(summary_codes(first)) == {0, 1, 2, 3} != GATE  # 4 and 5 left out
    assert check_words(1, summary_codes(second)[1]) == ["ERRORED"]
    assert code_tables(text) == {"compare": {0, 1}, "replay": {0}}
    ((verdict, cell),) = verdict_exit_rows(text)
    assert gate_exit_code(VERDICTS[verdict], "regressed") != int(re.findall(r": (\d+)\)", cell)[0])


def test_fail_on_and_the_gate_codes_come_from_the_gate_verdicts():
    """Issue 72 item 3: --fail-on's choices are the gate verdicts' `fails_from`, mildest choice first; a choice fails
    on the verdict it names (the mildest that exits 1) and on every worse one; a failing verdict exits with its own code
    (ERRORED 3 and INCOMPLETE 4 under every choice), a passing one 0; the commands offer exactly these choices."""
    import argparse
    import dataclasses

    from harness.cli import build_parser
    from harness.gate.config import GateConfig

    assert FAIL_ON == tuple(dict.fromkeys(v.fails_from for v in GateVerdict if v.fails_from))
    assert [v.rank for v in GateVerdict] == list(range(len(GateVerdict))) and GateVerdict.worst([]) == "IDENTICAL"
    for choice in FAIL_ON:
        failing = [v for v in GateVerdict if gate_exit_code(v, choice)]
        assert failing == list(GateVerdict)[: len(failing)], choice  # the worst verdicts, down to the one it names
        assert all(gate_exit_code(v, choice) == v.exit_code for v in failing), choice
        mildest = max((v for v in failing if v.exit_code == EXIT_FAIL), key=lambda v: v.rank)
        assert mildest.fails_from == choice, (choice, mildest)
    assert {gate_exit_code(v) for v in (GateVerdict.ERRORED, GateVerdict.INCOMPLETE)} == {3, 4}
    assert {v.exit_code for v in GateVerdict} | {EXIT_INVALID, INTERNAL_ERROR} == GATE
    assert {v.exit_code for v in ReplayVerdict} | {EXIT_INVALID, INTERNAL_ERROR} == REPLAY
    (field,) = [f for f in dataclasses.fields(GateConfig) if f.name == "fail_on"]
    assert field.default == DEFAULT_FAIL_ON
    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    for command in ("compare", "regress"):
        (action,) = [a for a in sub.choices[command]._actions if "--fail-on" in a.option_strings]
        assert tuple(action.choices) == FAIL_ON and action.default in (None, DEFAULT_FAIL_ON), command

"""The commands that write a section of a model's EVAL.md (docs/report.md, "EVAL.md sections and their provenance").

    python -m harness.report.<section> RUN... [--eval-md EVAL.md] [--note TEXT] [--command TEXT]

Each makes its section from run folders once, with its provenance line, and prints it. With --eval-md, the section's
figures go to `figures/<section>.json` beside that EVAL.md first (harness/report/figures_file.py), and the section
rendered from that file replaces its namesake there; other sections stay. Each section's module calls `section_main`
from its own `main` (robustness, grounding, faithfulness, phases, position, probes.reliance.report).
"""

from __future__ import annotations


def section_main(argv, prog: str, description: str, markdown, options: tuple = ()) -> int:
    """`python -m harness.report.<section> RUN... [--eval-md EVAL.md] [--note TEXT] [--command TEXT]`: make that
    section from run folders once (`markdown(records, note)`), with its provenance line (the command: --command, else
    this one with `options`, the caller's own options; the commit the runs recorded; the runs' machine) and print it.
    With --eval-md: its figures go to `figures/<section>.json` beside that EVAL.md first, and the section rendered
    from that file replaces its namesake there (other sections stay; harness/report/figures_file.py)."""
    import argparse
    import sys
    from pathlib import Path

    from harness.analysis.provenance import command_text, provenance_line
    from harness.analysis.runs import load_run

    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--eval-md", type=Path, default=None, help="write the section into this EVAL.md and its "
                        "figures file beside it [print it only]")
    parser.add_argument("--note", default="")
    parser.add_argument("--command", default=None, help="the command to name in the provenance line (a script that "
                        "calls this one) [this command]")
    args = parser.parse_args(argv)
    try:
        records = [load_run(p) for p in args.runs]  # a folder that is no run: one line naming it, EVAL.md untouched
        text = markdown(records, args.note)
    except ValueError as exc:  # runs that hold nothing for this section: one line, EVAL.md untouched
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    written = ["--eval-md", str(args.eval_md)] if args.eval_md else []
    command = args.command or command_text(prog, args.runs, [*written, *options])
    try:
        text = write_section(args.eval_md, text, provenance_line(command, [r.manifest for r in records]))
    except OSError as exc:  # a folder not writable, a full disk, a file where figures/ goes: one line, EVAL.md untouched
        print(f"{prog}: error: cannot write {exc.filename or args.eval_md}: {exc.strerror or exc}; give --eval-md a "
              "writable folder", file=sys.stderr)
        return 2
    print(text)
    return 0


def tables_section(heading: str, tables, empty: str):
    """`markdown(records, note)` for section_main where `tables(records)` gives a section's body: "## heading",
    the note, then the tables; ValueError(`empty`) where they are empty (the runs hold nothing for the section)."""
    def markdown(records, note: str) -> str:
        body = tables(records)
        if not body.strip():
            raise ValueError(empty)
        return "\n\n".join(x.strip("\n") for x in (heading, note, body) if x.strip()) + "\n"
    return markdown


def write_section(eval_md, text: str, provenance: str) -> str:
    """A section's Markdown ("## Heading", then its body) and provenance line -> the section as rendered from its
    figures document; with `eval_md`, that document is written to `figures/<section>.json` beside it first, and the
    section rendered from the file replaces its namesake in `eval_md` (other sections stay)."""
    from harness.files import replace_markdown_section
    from harness.report import figures_file

    doc = figures_file.figures(text, provenance)
    if eval_md is None:
        return figures_file.render(doc)
    doc = figures_file.read(figures_file.write(eval_md, doc))  # the section is what its figures file renders
    text = figures_file.render(doc)
    replace_markdown_section(eval_md, doc["section"], text)
    return text

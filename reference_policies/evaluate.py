"""Evaluation table of the reference policy from finished `octo-harness run` folders.

    python -m reference_policies.evaluate RUN_DIR [RUN_DIR ...] --out models/octo-reference-robosuite

Reads each run's results.jsonl (success per episode) and every episode's metrics.jsonl, and writes
eval.json (the figures file) and EVAL.md's top section rendered from it alone (`rerender(folder)` renders it
again): per task n, successes, rate, Wilson 95% interval (harness.measures.stats) and the target lift per layer:
for each camera, the fraction of that camera's attention on the target mask divided by the mask's area (1 = chance),
averaged over the steps where the target is visible, then over episodes.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from harness.analysis.provenance import command_text, provenance_line, with_provenance
from harness.bounded import read_json
from harness.measures.stats import wilson_interval
from harness.options import option
from reference_policies.options import Provenance, add_options, parse, values


def target_lift(metrics_path: Path) -> dict[str, np.ndarray]:
    """{camera: (layers,) mean over steps of mask_mass/target / mask_area/target} for one episode."""
    per_camera: dict[str, list[np.ndarray]] = {}
    with open(metrics_path) as f:
        for line in f:
            row = json.loads(line)
            for camera, masses in (row.get("mask_mass") or {}).items():
                area = ((row.get("mask_area") or {}).get(camera) or {}).get("target")
                mass = (masses or {}).get("target")
                if not area or mass is None:
                    continue
                per_camera.setdefault(camera, []).append(np.asarray(mass, np.float64) / area)
    return {camera: np.nanmean(np.stack(values), axis=0) for camera, values in per_camera.items()}


def summarise_runs(run_dirs: list[Path]) -> list[dict]:
    """One row per task: n, successes, rate, Wilson 95% CI, mean target lift per camera and layer, seeds."""
    rows = []
    for run in run_dirs:
        results = {}
        with open(run / "results.jsonl") as f:
            for line in f:
                r = json.loads(line)
                results[(r["task"], r["episode"])] = r  # the last line of a job wins
        by_task: dict[str, list[dict]] = {}
        for r in results.values():
            if r["status"] == "ok":
                by_task.setdefault(r["task"], []).append(r)
        for task, episodes in by_task.items():
            n = len(episodes)
            successes = sum(bool(e["success"]) for e in episodes)
            low, high = wilson_interval(successes, n)
            lifts: dict[str, list[np.ndarray]] = {}
            for e in episodes:
                path = run / e["directory"] / "metrics.jsonl"
                if path.is_file():
                    for camera, lift in target_lift(path).items():
                        lifts.setdefault(camera, []).append(lift)
            rows.append({
                "task": task, "run": run.name, "n": n, "successes": successes, "rate": successes / n if n else float("nan"),
                "ci_low": low, "ci_high": high, "seeds": [min(e["seed"] for e in episodes), max(e["seed"] for e in episodes)],
                "mean_steps": float(np.mean([e["steps"] for e in episodes])),
                "target_lift": {c: np.nanmean(np.stack(v), axis=0).round(3).tolist() for c, v in sorted(lifts.items())},
            })
    return rows


FIGURES = "eval.json"  # the figures file beside the model: the top section of its EVAL.md is rendered from it alone
# What a section says when its runs were not kept and no figures file holds its figures (tests/docs/test_eval_sections.py)
NOT_KEPT = "Figures file: none. This section's runs were not kept, so it cannot be re-rendered from figures."


def markdown(rows: list[dict], note: str = "", title: str = "octo-reference-robosuite", preface: str = "") -> str:
    """The top section of EVAL.md (no provenance line): the note, a verdict line over the tasks, the table per task
    and camera, and what target lift is, as a list."""
    layers = max((len(v) for r in rows for v in r["target_lift"].values()), default=0)
    header = "| task | n | successes | rate | Wilson 95% CI | seeds | camera | " + " | ".join(f"lift L{i}" for i in range(layers)) + " |"
    lines = [f"# {title}: evaluation", ""] + [text + "\n" for text in (preface, note) if text]
    if len(rows) > 1:  # the average over tasks (every task weighs the same) and the pooled interval
        n, successes = sum(r["n"] for r in rows), sum(r["successes"] for r in rows)
        low, high = wilson_interval(successes, n) if n else (float("nan"), float("nan"))
        average = float(np.mean([r["rate"] for r in rows]))
        lowest = min(rows, key=lambda r: r["rate"])
        lines += [f"Average over the {len(rows)} tasks: **{average:.1%}** ({successes}/{n} episodes, Wilson 95% "
                  f"[{low:.2f}, {high:.2f}]). Lowest task: {lowest['task']} at {lowest['rate']:.0%}.", ""]
    lines += [header, "|" + "---|" * (7 + layers)]
    for r in rows:
        cams = list(r["target_lift"].items()) or [("-", [])]
        for i, (camera, lift) in enumerate(cams):
            first = i == 0
            cells = [r["task"] if first else "", str(r["n"]) if first else "", str(r["successes"]) if first else "",
                     f"{r['rate']:.0%}" if first else "", f"[{r['ci_low']:.2f}, {r['ci_high']:.2f}]" if first else "",
                     f"{r['seeds'][0]}..{r['seeds'][1]}" if first else "", camera] + [f"{x:.2f}" for x in lift]
            lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Target lift, per camera and layer:",
              "- a camera's attention (readout rows, head mean) on the target object's mask, divided by the mask's area;",
              "- 1 = uniform attention;",
              "- mean over the steps where the target is visible, then over episodes;",
              "- L0 is the first transformer layer.",
              "", f"Figures: `{FIGURES}` beside this file. This section is rendered from it alone."]
    return "\n".join(lines) + "\n"


def figures(rows: list[dict], note: str, title: str, provenance: str, preface: str = "") -> dict:
    """The figures file (eval.json): everything the top section is rendered from, its provenance line included, so
    rendering it again needs neither the runs nor the checkout."""
    return {"title": title, "provenance": provenance, "preface": preface, "note": note, "tasks": rows}


def render(data: dict) -> str:
    """eval.json's figures -> the top section of EVAL.md, provenance line below the title."""
    text = markdown(data["tasks"], data.get("note", ""), data["title"], data.get("preface", ""))
    return with_provenance(text, data["provenance"])


def write_section(out: Path, data: dict) -> str:
    """Write the top section rendered from `data` into out/EVAL.md (the ## sections other scripts wrote stay)."""
    from harness.files import write_atomic

    eval_md = out / "EVAL.md"
    kept = ""  # sections written by other scripts (e.g. "## Faithfulness", scripts/faithfulness_reference.sh) stay
    if eval_md.is_file() and "\n## " in eval_md.read_text():
        kept = "\n## " + eval_md.read_text().split("\n## ", 1)[1]
    text = render(data)
    write_atomic(eval_md, lambda f: f.write((text + kept).encode()))
    return text


def rerender(out: Path) -> str:
    """Render out/EVAL.md's top section again from out/eval.json (no runs needed)."""
    return write_section(out, json.loads((out / FIGURES).read_text()))


def other_checkpoint(runs: list[Path], manifests: list[dict], out: Path) -> str | None:
    """One line naming the first run made with another checkpoint than the one in `out` (compared by the files'
    sizes and sha256, as the run recorded them), or None. An `out` that holds no checkpoint is not checked."""
    if not (out / "config.json").is_file():
        return None
    from harness.run.protocol import model_fingerprint

    files = model_fingerprint(str(out))[1]["files"]
    for run, manifest in zip(runs, manifests):
        recorded = ((manifest.get("model") or {}).get("fingerprint") or {}) if isinstance(manifest, dict) else {}
        if isinstance(recorded, dict) and recorded.get("kind") == "files" and recorded.get("files") != files:
            return (f"{run} was made with another checkpoint ({recorded.get('root')}) than the one in {out}: pass "
                    "--out the folder the runs evaluated")
    return None


@dataclass(frozen=True)
class EvaluateOptions:
    out: Path = option(Path("models/octo-reference-robosuite"), "--out", "the checkpoint folder the runs evaluated "
                       "(EVAL.md and eval.json are written there)", type=Path)


def command_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m reference_policies.evaluate", description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="octo-harness run folders")
    add_options(parser, (EvaluateOptions, Provenance))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = command_parser()
    given, options = parse(parser, EvaluateOptions, argv)
    made = Provenance(**values(Provenance, given))
    args = argparse.Namespace(runs=given.runs, out=options.out, note=made.note, command=made.command)
    try:  # run folders are untrusted: the project's bounded reader (size and nesting checked)
        manifests = [read_json(run / "manifest.json", what="manifest.json") if (run / "manifest.json").is_file() else {}
                     for run in args.runs]
    except (OSError, ValueError) as e:  # UnicodeDecodeError and BoundsError are ValueErrors
        parser.error(f"a run's manifest.json is unreadable ({e}); pass finished `octo-harness run` folders")
    mismatch = other_checkpoint(args.runs, manifests, args.out)
    if mismatch:
        parser.error(mismatch)
    rows = summarise_runs(args.runs)
    args.out.mkdir(parents=True, exist_ok=True)
    command = args.command or command_text("python -m reference_policies.evaluate", args.runs, ["--out", str(args.out)])
    previous = args.out / FIGURES  # a preface written into the figures file (what the folder is) stays
    preface = (read_json(previous, what=FIGURES).get("preface") or "") if previous.is_file() else ""
    data = figures(rows, args.note, args.out.resolve().name, provenance_line(command, manifests), preface)
    from harness.files import write_atomic

    write_atomic(args.out / FIGURES, lambda f: f.write(json.dumps(data, indent=2).encode()))
    text = write_section(args.out, data)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

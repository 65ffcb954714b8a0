"""What two runs' numbers can and cannot say about each other: platforms, inputs and step-0 model numerics.

compare's statistical verdict is about outcomes; this block says what else is known, from what the runs
recorded (pure functions over manifests and the per-pair details of harness.analysis.compare):

- platform: the two manifests' `platform_fingerprint`s (harness/runfolder/platform.py) and the numerics-relevant
  fields in which they differ. Same fingerprint: trajectories should be bit-identical, so a difference is
  the candidate's. Different: float noise of the other CPU, XLA or renderer, amplified by contact-rich
  simulation, can send an unchanged model down another trajectory, so diverging trajectories are expected
  and are the platform's, not the model's.
- inputs: per pair, for how many leading steps both arms fed the policy bit-identical inputs (the per-step
  `input_hash/<key>` digests in actions.npz). At step 0 (same seed) they agree unless the renderers differ.
- model numerics at step 0: where both arms saw identical step-0 inputs, the step-0 chunk and readout
  attention differ only by the model and float noise: EQUIVALENT when within the replay tolerances
  (harness.analysis.equivalence; the action change here is in the runs' own action units, as compare has no
  model statistics; replay normalises), CHANGED beyond them, IDENTICAL when bit-equal, UNKNOWN when no pair saw
  identical step-0 inputs (then `octo-harness replay` on recorded inputs decides).
"""

from __future__ import annotations

import re

import numpy as np

from harness.analysis.equivalence import Tolerances
from harness.runfolder.platform import platform_differences
from harness.verdicts import Step0Verdict


def leading_equal(a: np.ndarray, b: np.ndarray) -> int:
    """(steps,) x2 -> number of leading positions where they are equal (over the shorter length)."""
    n = min(len(a), len(b))
    unequal = np.flatnonzero(np.asarray(a[:n]) != np.asarray(b[:n]))
    return int(unequal[0]) if unequal.size else n


def input_agreement(a: dict, b: dict) -> dict | None:
    """Arrays of two episodes ("actions.npz:input_hash/<key>" -> (steps,) uint64) -> {"keys", "leading_steps",
    "step0_same"}, or None when either run recorded no input digests."""
    prefix = "actions.npz:input_hash/"
    keys = sorted(k for k in a if k.startswith(prefix))
    if not keys or keys != sorted(k for k in b if k.startswith(prefix)):
        return None
    leading = min(leading_equal(a[k], b[k]) for k in keys)
    steps = min(len(a[keys[0]]), len(b[keys[0]]))
    return {"keys": [k[len(prefix):] for k in keys], "leading_steps": leading, "compared_steps": steps,
            "step0_same": leading > 0}


def platform_block(baseline_manifest: dict, candidate_manifest: dict) -> dict:
    fa, fb = baseline_manifest.get("platform_fingerprint"), candidate_manifest.get("platform_fingerprint")
    known = fa is not None and fb is not None
    return {"baseline": fa, "candidate": fb, "same": known and fa == fb, "known": known,
            "differs_in": platform_differences(baseline_manifest.get("platform"), candidate_manifest.get("platform"))
            if known and fa != fb else []}


def step0_numerics(pairs: list[dict], tolerances: Tolerances) -> dict:
    """pairs: compare's per-pair details with "inputs" (input_agreement), "action_max_abs_step0" and
    "js_step0_max" -> the step-0 model-numerics verdict (see the module docstring)."""
    same = [p for p in pairs if (p.get("inputs") or {}).get("step0_same") and "action_max_abs_step0" in p]
    if not same:
        return {"verdict": Step0Verdict.UNKNOWN, "pairs_same_step0_inputs": 0, "pairs": len(pairs),
                "action_change_max": None, "attention_js_max": None, "tolerances": vars(tolerances).copy()}
    action = max(p["action_max_abs_step0"] for p in same)
    js = max(p.get("js_step0_max", 0.0) for p in same)
    if action == 0.0 and js == 0.0:
        verdict = Step0Verdict.IDENTICAL
    elif action <= tolerances.action and js <= tolerances.attention_js:
        verdict = Step0Verdict.EQUIVALENT
    else:
        verdict = Step0Verdict.CHANGED
    return {"verdict": verdict, "pairs_same_step0_inputs": len(same), "pairs": len(pairs),
            "action_change_max": action, "attention_js_max": js, "tolerances": vars(tolerances).copy()}


def provenance(baseline_manifest: dict, candidate_manifest: dict, pairs: list[dict],
               tolerances: Tolerances | None = None, differs: dict | None = None) -> dict:
    """The provenance block of compare.json and the sentence its report leads with. differs: compare's
    `what_differs` (None: the model is what differs)."""
    tolerances = tolerances or Tolerances()
    platform = platform_block(baseline_manifest, candidate_manifest)
    numerics = step0_numerics(pairs, tolerances)
    agreements = [p["inputs"] for p in pairs if p.get("inputs")]
    inputs = {"pairs_with_digests": len(agreements), "pairs": len(pairs),
              "step0_same": sum(a["step0_same"] for a in agreements),
              "leading_steps_min": min((a["leading_steps"] for a in agreements), default=None),
              "leading_steps_max": max((a["leading_steps"] for a in agreements), default=None)}
    return {"platform": platform, "inputs": inputs, "step0_numerics": numerics,
            "summary": summary_sentence(platform, inputs, numerics, differs)}


def summary_sentence(platform: dict, inputs: dict, numerics: dict, differs: dict | None = None) -> str:
    """One plain line: what the model numerics are, and whose diverging trajectories are. With `differs` naming
    settings other than the model that differ (an intervention), the numerics and the differences are said to be
    theirs, not the model's alone."""
    cause = (differs or {}).get("cause", "the candidate's")
    other = (differs or {}).get("other") or []
    if not inputs["pairs_with_digests"]:
        seen = "the runs recorded no input digests (made before provenance), so whether both arms saw the same inputs is unknown"
    else:
        seen = (f"both arms fed the policy identical inputs at step 0 in {inputs['step0_same']}/{inputs['pairs_with_digests']} "
                f"pairs, for {inputs['leading_steps_min']}-{inputs['leading_steps_max']} leading steps")
    verdict = numerics["verdict"]
    if other:
        names = ", ".join(o["field"] for o in other)
        model = (f"step-0 numerics: {verdict} but not the model's alone (the protocols differ in {names}; "
                 "`octo-harness replay` isolates a model change)")
    elif verdict == Step0Verdict.UNKNOWN:
        model = (f"model numerics: {Step0Verdict.UNKNOWN} (no pair saw identical step-0 inputs; replay the baseline's "
                 "recorded inputs with `octo-harness replay`)")
    else:
        tol = numerics["tolerances"]
        model = (f"model numerics at step 0: {verdict} (largest change: action {numerics['action_change_max']:.3g}, "
                 f"tolerance {tol['action']:g}; attention JS {numerics['attention_js_max']:.3g} bits, tolerance "
                 f"{tol['attention_js']:g})")
    if not platform["known"]:
        where = "platform: unknown for one run (made before provenance)"
    elif platform["same"]:
        where = f"platform: the same (bit-identical trajectories are expected; any difference is {cause})"
    else:
        where = (f"platform: different ({', '.join(platform['differs_in']) or 'fingerprint'}); trajectories that diverge "
                 "after identical step-0 numerics are this float noise amplified by the closed loop, the platform's, "
                 "not the model's" + (f"; other differences are {cause}" if other else ""))
    return f"{model}; {seen}; {where}"


def summary_points(summary: str) -> list[str]:
    """compare's provenance sentence (harness.analysis.provenance.summary_sentence) as its parts, split at '; '
    outside parentheses: one short bullet each (model numerics, inputs, platform), every figure kept."""
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(summary):
        depth += (ch == "(") - (ch == ")")
        if depth == 0 and summary.startswith("; ", i):
            parts.append(summary[start:i])
            start = i + 2
    parts.append(summary[start:])
    return [part.strip().rstrip(".") for part in parts if part.strip()]


# ---- the provenance line of a results section (EVAL.md, model cards; tests/docs/test_provenance.py) ----------------

# "Provenance: command `...`; commit `<hash>` (...); machine: ...." on a line of its own; group 1: the commit
PROVENANCE_LINE = re.compile(r"^Provenance: command `[^`]+`; commit `([0-9a-f]{7,40})`[^;]*; machine: \S.*\.$", re.M)

def machine_text(platforms: list) -> str:
    """Run manifests' `platform` dicts -> "Intel(R) Xeon(R) Processor (x86_64), 2 cores, CPU only" (the GPU's kind
    instead of "CPU only" where JAX ran on one); several machines are each named with their run count, and runs that
    recorded none are counted."""
    names: dict[str, int] = {}
    unrecorded = 0
    for info in platforms:
        if not isinstance(info, dict) or not isinstance(info.get("cpu"), dict):
            unrecorded += 1
            continue
        cpu, jax = info["cpu"], info.get("jax") if isinstance(info.get("jax"), dict) else {}
        device = (f"GPU {jax.get('device_kind')}" if str(jax.get("backend", "")).lower() in ("gpu", "cuda", "rocm")
                  else "CPU only")
        name = f"{cpu.get('model', 'unknown CPU')} ({info.get('machine', '?')}), {cpu.get('cores', '?')} cores, {device}"
        names[name] = names.get(name, 0) + 1
    if not names:
        return "not recorded in the runs' manifests"
    parts = list(names) if len(names) == 1 and not unrecorded else [f"{n} ({k} runs)" for n, k in names.items()]
    return " and ".join(parts + ([f"{unrecorded} runs without a recorded platform"] if unrecorded else []))


def checkout_commit(repo=None) -> tuple[str | None, bool]:
    """(`git rev-parse HEAD` of the checkout, whether tracked files differ from it); (None, False) outside git."""
    import subprocess
    from pathlib import Path

    repo = Path(repo) if repo is not None else Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=30)
        if head.returncode != 0:
            return None, False
        status = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=60)
        return head.stdout.strip(), bool(status.stdout.strip())
    except (OSError, subprocess.SubprocessError):
        return None, False


def provenance_line(command: str, manifests: list, repo=None) -> str:
    """"Provenance: command `...`; commit `<hash>` (...); machine: ...." for a section made from runs: the command
    that made it, the commit that produced the figures (the one commit the runs recorded; else the checkout that
    wrote the section, with the runs' commits), and the machine from the runs' manifests (`machine_text`). No ';' inside the parts: the line's fields split on it."""
    head, dirty = checkout_commit(repo)
    recorded = sorted({m.get("git_commit") for m in manifests if isinstance(m, dict) and m.get("git_commit")})
    if len(recorded) == 1:  # the runs name the commit that produced the figures: the line names it (issue 67 item 6)
        notes = ["the commit the runs recorded, which produced these figures"]
        if head and (head != recorded[0] or dirty):
            notes.append(f"this section written at `{head[:12]}`" + (" with uncommitted changes" if dirty else ""))
        commit = f"commit `{recorded[0][:12]}` ({', '.join(notes)})"
    else:
        notes = ["the checkout that wrote this section" + (", with uncommitted changes" if dirty else "")]
        notes.append("the runs recorded " + ", ".join(f"`{c[:12]}`" for c in recorded) if recorded
                     else "the runs recorded no commit")
        commit = f"commit `{head[:12]}` ({', '.join(notes)})" if head else "commit unknown (not a git checkout)"
    machine = machine_text([m.get("platform") if isinstance(m, dict) else None for m in manifests])
    return f"Provenance: command `{command.replace('`', chr(39)).replace(';', ',')}`; {commit}; machine: {machine}."


def command_text(prog: str, runs, rest: list[str]) -> str:
    """The command that makes a section, for its provenance line: `prog RUN... rest`, the runs named by their common
    folder and count when there are more than 3."""
    import os
    import shlex

    runs = [str(r) for r in runs]
    if len(runs) > 3:
        parent = os.path.commonpath([os.path.abspath(r) for r in runs])
        named = f"{os.path.relpath(parent)}/<{len(runs)} runs>"
    else:
        named = " ".join(runs)
    return " ".join([prog, named, shlex.join(rest)] if rest else [prog, named])


def with_provenance(text: str, line: str) -> str:
    """A Markdown section ("## Heading\n..." or "# Title\n...") with its provenance line right below the heading."""
    heading, _, body = text.partition("\n")
    return f"{heading}\n\n{line}\n\n{body.lstrip(chr(10))}"

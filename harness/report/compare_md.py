"""Markdown summary of a comparison (a CompareResult, compare.json's content -> text fit for a CI log or a
pull-request comment)."""
from __future__ import annotations

import math

from harness.analysis.compare_result import CompareResult, OutcomeBlock, Rate
from harness.analysis.outcomes import UNDECIDED
from harness.analysis.provenance import summary_points


def _num(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}g}" if isinstance(value, float) else str(value)


def _errored(count) -> str:
    return f" ({count} errored)" if count else ""


def _rate(rate: Rate) -> str:
    """successes/n = rate [interval], n = pairs with an outcome in both arms, this arm's errored episodes beside."""
    if not rate.n:
        return "n/a" + _errored(rate.errored)
    return (f"{rate.successes}/{rate.n} = {rate.rate:.2f} [{rate.ci_low:.2f}, {rate.ci_high:.2f}]"
            + _errored(rate.errored))


def to_decide(block: OutcomeBlock, more: str = "more") -> str:
    """The "to decide" cell: pairs an UNDERPOWERED or SUSPECT table would need (plug-in estimate)."""
    if block.verdict not in UNDECIDED:
        return ""
    needed = block.more_pairs_needed
    return "> 100000" if needed is None else f"~{needed} {more}"


def pairs_cell(block: OutcomeBlock) -> str:
    """n, with the errored pairs left out beside it."""
    errored = block.errored_pairs or 0
    return f"{block.pairs}" + (f" (+{errored} errored)" if errored else "")


def _difference(block: OutcomeBlock) -> str:
    if block.difference is None:
        return "n/a"
    low, high = block.difference_ci
    return f"{block.difference:+.2f} [{low:+.2f}, {high:+.2f}]"


def _row(name: str, block: OutcomeBlock) -> str:
    return (f"| {name} | {pairs_cell(block)} | {_rate(block.baseline)} | {_rate(block.candidate)} | "
            f"{_difference(block)} | {_num(block.mcnemar_p)} ({_num(block.mcnemar_p_holm)}) | "
            f"**{block.verdict}** | {to_decide(block)} |")


def difference_label(result: CompareResult) -> str:
    """The difference intervals' method and confidence, e.g. "95% Newcombe" or "98.3% Newcombe, simultaneous
    over 3 tables" (Bonferroni over the Holm family)."""
    level = result.outcomes.overall.difference_confidence
    family = result.outcomes.holm_family
    return f"{100 * level:.3g}% Newcombe" + (f", simultaneous over {family} tables" if family > 1 else "")


def _layers(values) -> str:
    return ", ".join(_num(float(v), 2) for v in values) if values is not None else "n/a"


def markdown_summary(result: CompareResult, exit_code: int | None = None) -> str:
    """The comparison as Markdown: verdict, outcome table, drift and what was left out."""
    cfg, base, cand = result.config, result.baseline, result.candidate
    confidence = f"{100 * (1 - cfg.alpha):g}%"
    lines = [
        f"## octo-harness compare: {result.verdict}",
        "",
        f"baseline `{base.run}` ({base.model}) vs candidate `{cand.run}` ({cand.model}): "
        f"{result.pairs} pairs by (task, seed); max drop {cfg.max_drop:g}, alpha {cfg.alpha:g}.",
    ]
    for arm in (base, cand):
        if arm.random_weights:
            lines.append(f"> NOTE: `{arm.run}` uses RANDOM weights ({arm.model}).")
    ident = result.identical
    if ident.identical:
        lines += ["", ("Every paired array is bit-equal" if not ident.atol else
                       f"Every paired array is equal within {ident.atol:g}")
                  + f" and every outcome is the same ({ident.steps_compared})."]
        if ident.derived_measures:
            lines += ["", "Derived measures: " + ident.derived_measures.note + "."]
    else:
        lines += ["", f"Not identical: {ident.pairs_identical}/{result.pairs} pairs identical; first difference: "
                      f"{ident.first_difference}."]
    lines += ["", "**Provenance:**", *(f"- {point}." for point in summary_points(result.provenance.summary))]
    lines += [
        "",
        f"| task | pairs | baseline success [{confidence} Wilson] | candidate success | difference = candidate - "
        f"baseline [{difference_label(result)}] | McNemar p (Holm) | verdict | to decide |",
        "|---|---:|---|---|---|---|---|---|",
    ]
    outcomes = result.outcomes
    for task, block in outcomes.tasks.items():
        lines.append(_row(task, block))
    if len(outcomes.tasks) > 1:
        lines.append(_row("**pooled**", outcomes.overall))
    if outcomes.notes:
        lines += [""] + [f"- {note}" for note in outcomes.notes]

    drift = result.drift
    s0 = drift.step0.overall
    lines += ["", f"**Step-0 drift** ({result.differs.drift_label}):",
              f"- action chunk: mean L2 {_num(s0.action_l2)}, max |difference| {_num(s0.action_max_abs)}"]
    if s0.js_layer is not None:
        lines.append(f"- readout attention Jensen-Shannon (bits, mean over heads) per layer: {_layers(s0.js_layer)}")
    else:
        lines.append(f"- readout attention: not comparable ({_why_no_attention(result)})")
    for obs, change in s0.target_lift_change.items():
        lines.append(f"- target lift change ({obs}) per layer: {_layers(change)}")
    if drift.first_steps:
        steps = drift.first_steps
        lines.append(f"- first {len(steps)} steps, attention JS: "
                     + ", ".join(_num(s.js_mean, 2) for s in steps)
                     + "; action L2: " + ", ".join(_num(s.action_l2, 2) for s in steps))
    whole = drift.whole_episode
    lines.append(f"- whole episodes (confounded by diverging trajectories): attention JS {_num(whole.js_mean)}, "
                 f"action L2 {_num(whole.action_l2)}")
    missing = result.missing_pairs
    if missing.candidate or missing.baseline:
        lines += ["", f"Left out: {len(missing.candidate)} pairs missing from the candidate, "
                      f"{len(missing.baseline)} missing from the baseline."]
    unverified = [f"{arm.run} {arm.unverified}" for arm in (base, cand) if arm.unverified]
    if unverified:
        lines.append("Files read unverified (rows made before sizes and digests were recorded): "
                     + ", ".join(unverified) + " episodes.")
    errors = (base.errors, cand.errors)
    if any(errors):
        lines.append(f"Episodes that raised (no outcome; their pairs are left out of n and counted as errored): "
                     f"baseline {errors[0]}, candidate {errors[1]}.")
    if exit_code is not None:
        lines += ["", f"Exit code {exit_code}."]
    return "\n".join(lines) + "\n"


def _why_no_attention(result: CompareResult) -> str:
    """Why no pair has an attention drift: a pair's note (a run without attention) or different token maps."""
    from harness.analysis.protocol_fields import ATTENTION_NOTES

    notes = [p.attention_note for p in result.pair_details if p.attention_note in ATTENTION_NOTES.values()]
    return notes[0].split(":")[0] if notes else "different token maps"

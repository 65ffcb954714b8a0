"""The closed-loop half of the report's Faithfulness section (harness.report.faithfulness): runs given together whose
protocols differ only in `policy.intervention` (same model, tasks, seeds) are paired with the plain run, and each
mask-top:K run with the mask-random:K run (is the map better than chance at finding what the policy needs?): success
of each arm (Wilson), the paired difference (Newcombe's interval for paired proportions) and the exact McNemar
p-value, per task, and pooled over the tasks of an intervention.

`intervention_rows(runs)` -> rows of INTERVENTION_COLUMNS (interventions.csv).
"""

from __future__ import annotations

import json

from harness.analysis.paired import PairedCounts, mcnemar_exact, newcombe_paired_interval
from harness.measures.stats import wilson_interval

INTERVENTION_COLUMNS = ("run", "baseline_run", "intervention", "task", "pairs", "baseline_successes", "baseline_rate",
                        "baseline_ci_low", "baseline_ci_high", "successes", "rate", "ci_low", "ci_high",
                        "difference", "difference_ci_low", "difference_ci_high", "mcnemar_p")


def run_policy(run) -> dict:
    """The policy settings of a run's protocol (RunData or RunRecord)."""
    record = getattr(run, "record", run)
    return dict((record.manifest.get("protocol") or {}).get("policy") or {})


def _arm_key(run) -> tuple:
    """What must agree for two runs to be arms of one intervention experiment (all but the intervention)."""
    record = getattr(run, "record", run)
    protocol = dict(record.manifest.get("protocol") or {})
    policy = {k: v for k, v in (protocol.get("policy") or {}).items()
              if k not in ("intervention", "attribution", "faithfulness_every", "faithfulness_fill")}
    return json.dumps({"model_fingerprint": protocol.get("model_fingerprint"), "max_steps": protocol.get("max_steps"),
                       "env": protocol.get("env"), "policy": policy}, sort_keys=True)


def intervention_rows(runs) -> list[tuple]:
    """Rows of INTERVENTION_COLUMNS: each run with an intervention against the plain run of the same experiment,
    and each mask-top:K run against the mask-random:K run of the same experiment (is the map better than chance?).
    When an intervention was run on several tasks (one run per task or one run of several), a "pooled" row per
    (intervention, comparison) pools its pairs over the tasks (task "pooled", run and baseline_run joined by '+')."""
    plain, random_k = {}, {}  # (experiment, task) -> the run holding that task
    for run in runs:
        spec = run_policy(run).get("intervention")
        for task in getattr(run, "record", run).tasks:
            if not spec:
                plain.setdefault((_arm_key(run), task), run)
            elif spec.startswith("mask-random:"):
                random_k.setdefault((_arm_key(run), _masked_count(spec), task), run)
    out, pooled = [], {}
    for run in runs:
        spec = run_policy(run).get("intervention")
        if not spec:
            continue
        for task in getattr(run, "record", run).tasks:
            bases = [("plain", plain.get((_arm_key(run), task)))]
            if spec.startswith("mask-top:"):
                bases.append((f"mask-random:{_masked_count(spec)[0]}",
                              random_k.get((_arm_key(run), _masked_count(spec), task))))
            for kind, base in bases:
                if base is None:
                    continue
                for _, b, c in _paired_outcomes(base, run, task):
                    out.append(_row(arm_name(run), arm_name(base), spec, task, b, c))
                    entry = pooled.setdefault((spec, kind), ([], [], [], [], set()))
                    entry[0].append(arm_name(run))
                    entry[1].append(arm_name(base))
                    entry[2].extend(b)
                    entry[3].extend(c)
                    entry[4].add(task)
    for (spec, _), (names, base_names, b, c, tasks) in pooled.items():
        if len(tasks) > 1:
            out.append(_row("+".join(dict.fromkeys(names)), "+".join(dict.fromkeys(base_names)), spec, "pooled", b, c))
    return out


def arm_name(run) -> str:
    """The name a run's rows give it: its label, else its folder's name."""
    return getattr(run, "label", None) or getattr(run, "record", run).name


def _masked_count(spec: str) -> tuple[str, str]:
    """(K, camera) of a mask spec: mask-top:4:attention:2@image_wrist -> ("4", "image_wrist")."""
    body, _, camera = spec.partition("@")
    return body.split(":")[1], camera


def _paired_outcomes(base, run, task: str) -> list[tuple[str, list[bool], list[bool]]]:
    """[(task, baseline successes, run successes)] over the task's seeds both runs finished without error ([] if none)."""
    b_eps = {e.seed: e for e in getattr(base, "record", base).episodes if e.ok and e.task == task}
    c_eps = {e.seed: e for e in getattr(run, "record", run).episodes if e.ok and e.task == task}
    seeds = sorted(set(b_eps) & set(c_eps))
    if not seeds:
        return []
    return [(task, [bool(b_eps[s].success) for s in seeds], [bool(c_eps[s].success) for s in seeds])]


def _row(name: str, base_name: str, spec: str, task: str, b: list[bool], c: list[bool]) -> tuple:
    counts = PairedCounts.from_outcomes(b, c)
    n = len(b)
    lo, hi = newcombe_paired_interval(counts.both, counts.candidate_only, counts.baseline_only, counts.neither)
    return (name, base_name, spec, task, n, sum(b), sum(b) / n, *wilson_interval(sum(b), n), sum(c), sum(c) / n,
            *wilson_interval(sum(c), n), (sum(c) - sum(b)) / n, lo, hi,
            mcnemar_exact(counts.baseline_only, counts.candidate_only))

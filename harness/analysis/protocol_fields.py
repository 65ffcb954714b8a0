"""What two runs' protocols differ in: whether the runs can be paired, what the drift and provenance lines name,
and which measures only one run took (the probes a protocol turns on; attention, which a policy without it lacks:
`attention_sides`, compared on the arrays both runs have, `shared_arrays`).

Fields fall in four kinds:
  the model      MODEL_FIELDS: what a comparison is usually about;
  neutral        fields that change neither the policy's inputs nor its actions: SAME_ACTIONS (bit-identical by
                 design: which tasks and seeds, the outputs, the batch shape) and the option fields of every probe
                 that never changes actions, derived from the probe registry (harness.probes.registry), so a probe
                 added there is neutral here with no edit;
  named          fields that may differ but change what the policy computes (an intervention, a dataset key): the
                 drift and provenance lines name them;
  everything else changes outcomes (env options, max steps, execution, action space, cameras, instruction, goals...):
                 the runs cannot be paired (`incompatible_fields`).
"""

from __future__ import annotations

import json

from harness.probes.registry import measured, measuring_fields
from harness.runfolder.schema import flatten

MODEL_FIELDS = ("model", "model_fingerprint", "text_tokenizer", "model_is_random", "model_note")
SAME_ACTIONS = ("tasks", "episodes", "seed", "outputs", "harness_version", "git_commit", "versions",
                "policy.full_attention", "policy.inference_batch")
# an intervention run against a plain one: the change is what is measured; legacy manifests (before the run store)
# keep the dataset key at the top level
NAMED = ("policy.dataset_key", "policy.intervention", "dataset_key")


def neutral_fields() -> tuple[str, ...]:
    """The fields that change neither the policy's inputs nor its actions (SAME_ACTIONS and every measuring probe's
    options, as "policy.<field>")."""
    return SAME_ACTIONS + tuple(f"policy.{name}" for name in measuring_fields())


def may_differ() -> tuple[str, ...]:
    """The protocol fields two comparable runs may differ in: the model, the neutral fields and the named ones."""
    return MODEL_FIELDS + neutral_fields() + NAMED


def _under(key: str, fields) -> bool:
    return any(key == f or key.startswith(f + ".") for f in fields)


def one_side_measures(baseline: dict, candidate: dict) -> dict[str, tuple[str, ...]]:
    """{"baseline": probes only the baseline's protocol turns on, "candidate": only the candidate's}: empty when both
    measured the same."""
    a, b = (measured((p or {}).get("policy") or {}) for p in (baseline, candidate))
    return {"baseline": tuple(n for n in a if n not in b), "candidate": tuple(n for n in b if n not in a)}


def one_side_line(sides: dict[str, tuple[str, ...]]) -> str | None:
    """One line naming the measures only one run has (None when there are none)."""
    parts = [f"{', '.join(names)} only in the {arm}" for arm, names in sides.items() if names]
    if not parts:
        return None
    return (f"measures only one run took: {'; '.join(parts)} (measured beside the actions; compared where both "
            "runs have them)")


ATTENTION = "attention.npz:readout_attention"


def attention_sides(a: dict, b: dict) -> str:
    """Which arm's arrays hold readout attention: "both", "baseline", "candidate" or "neither"."""
    return {(True, True): "both", (True, False): "baseline", (False, True): "candidate",
            (False, False): "neither"}[(ATTENTION in a, ATTENTION in b)]


ATTENTION_NOTES = {"baseline": "only the baseline has attention (the candidate's policy gives none): compared on "
                               "actions, rewards and outcomes",
                   "candidate": "only the candidate has attention (the baseline's policy gives none): compared on "
                                "actions, rewards and outcomes",
                   "neither": "neither run has attention (policies without it): compared on actions, rewards and "
                              "outcomes"}


def shared_arrays(a: dict, b: dict) -> tuple[dict, dict]:
    """Both arms' arrays with the attention.npz arrays only one arm has left out (one arm has no attention)."""
    def keep(x: dict, y: dict) -> dict:
        return {k: v for k, v in x.items() if not k.startswith("attention.npz:") or k in y}
    return keep(a, b), keep(b, a)


def with_attention_sides(one_side: dict[str, tuple[str, ...]], details: list[dict]) -> tuple[dict, str | None]:
    """`one_side_measures` with "attention" added to the arm that alone has it in some pair (the other arm's policy
    gives none), and the one line for pairs where neither arm has attention (None otherwise)."""
    notes = {d.get("attention_note") for d in details}
    alone = [arm for arm in ("baseline", "candidate") if ATTENTION_NOTES[arm] in notes]
    one_side = {arm: (("attention",) if arm in alone else ()) + tuple(names) for arm, names in one_side.items()}
    neither = ATTENTION_NOTES["neither"] in notes and not alone
    return one_side, f"attention: {ATTENTION_NOTES['neither']}" if neither else None


_MISSING = object()


def _differing(baseline: dict, candidate: dict) -> tuple[dict, dict, list[str]]:
    """Both protocols flattened to dotted keys, and the sorted keys whose values differ (the legacy top-level
    "execution" left out: `incompatible_fields` names it only where no policy block differs)."""
    a, b = flatten(json.loads(json.dumps(baseline))), flatten(json.loads(json.dumps(candidate)))
    return a, b, sorted(k for k in set(a) | set(b) if k != "execution" and a.get(k, _MISSING) != b.get(k, _MISSING))


def incompatible_fields(baseline: dict, candidate: dict) -> list[str]:
    """Dotted protocol fields that differ and change outcomes (everything but `may_differ()`)."""
    a, b, differ = _differing(baseline, candidate)
    legacy = not any(k.startswith("policy.") for k in differ)
    if legacy and a.get("execution", _MISSING) != b.get("execution", _MISSING):
        differ.append("execution")  # legacy manifests have no policy block
    differ = [k for k in differ if not any(k.startswith(d + ".") for d in differ)]  # None vs {...}: name the parent
    allowed = may_differ()
    return [k for k in differ if not _under(k, allowed)]


def _shown(value) -> str:
    return "none" if value is None else json.dumps(value) if not isinstance(value, str) else value


def what_differs(baseline: dict, candidate: dict) -> dict:
    """What the protocols of two comparable runs differ in, for the drift and provenance lines: {"model": the model
    differs, "other": [{"field", "baseline", "candidate"}] (fields that change the policy's inputs or actions but are
    not the model: an intervention, ...), "cause": who a difference belongs to, "drift_label": what the step-0 drift
    measures}."""
    a, b, differ = _differing(baseline, candidate)
    neutral = neutral_fields()
    model = any(_under(k, MODEL_FIELDS) for k in differ)
    parents = {k.rsplit(".", 1)[0] for k in differ if "." in k}
    other = [{"field": k, "baseline": a.get(k), "candidate": b.get(k)} for k in differ
             if not _under(k, MODEL_FIELDS) and not _under(k, neutral) and k not in parents]
    named = ", ".join(f"{o['field']} ({_shown(o['baseline'])} -> {_shown(o['candidate'])})" for o in other)
    if other and model:
        cause = f"the candidate's model and {named} together"
        drift = (f"same seed and scene; the arms differ in the model and in {named}: these numbers measure both "
                 "together, not the model alone")
    elif other:
        cause = f"{named}, not the model (both arms run the same model)"
        drift = (f"same seed and scene; the arms differ in {named}, not in the model: these numbers measure that "
                 "difference, not a model change")
    elif model:
        cause = "the candidate's"
        drift = "same seed, identical observation: the model change alone"
    else:
        cause = "float noise or the platform's (the protocols differ in nothing that changes actions)"
        drift = "same seed, identical observation, same model: any difference is float noise or the platform's"
    return {"model": model, "other": other, "cause": cause, "drift_label": drift}

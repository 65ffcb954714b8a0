"""The data sinks: an episode's arrays (`.npz`) and lines (`.jsonl`), the files a run's rows digest.

One sink per file (shapes in harness.outputs.writers' docstring), each written atomically when the episode closes:

  AttentionArrays   attention.npz    readout attention, token map, per-step metrics, mask fractions, measures, phases
  ActionArrays      actions.npz      predicted and executed actions, reward, success, inferred, input digests
  InputArrays       inputs.npz       the policy's inputs per step (OutputOptions.record_inputs), for replay
  MetricLines       metrics.jsonl    one row per step: ids, reward, success, phase, metrics, timings

The per-step probes' files are written by the sinks their probes declare (harness.probes: attribution.npz,
faithfulness.jsonl, controls.npz and the rest), with `write_lines` and `json_safe` as here.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from harness.measures.episode import measure_arrays
from harness.measures.attention import mask_fractions
from harness.files import json_safe, write_atomic
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink, phase_names_of
from harness.policy import input_digest


def stack_steps(per_step: list[dict[str, np.ndarray]], prefix: str) -> dict[str, np.ndarray]:
    """[{name: (...)} per step] -> {prefix + name: (steps, ...) float32}; steps that lack a name hold nan."""
    names: dict[str, tuple] = {}
    for m in per_step:
        for k, v in m.items():
            names.setdefault(k, np.shape(v))
    out = {}
    for name, shape in names.items():
        rows = [np.asarray(m[name], np.float32) if name in m else np.full(shape, np.nan, np.float32) for m in per_step]
        out[prefix + name] = np.stack(rows)
    return out


def nest(flat: dict[str, Any]) -> dict[str, Any]:
    """{"a/b/c": v} -> {"a": {"b": {"c": v}}}."""
    out: dict[str, Any] = {}
    for key, value in flat.items():
        *parents, leaf = key.split("/")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out


def write_lines(path, lines: list[str]) -> None:
    write_atomic(path, lambda f: f.write(("\n".join(lines) + "\n" if lines else "").encode()))


class AttentionArrays(Sink):
    """attention.npz: step, tokens/*, metrics/*, mask_fraction/*, readout_attention, measures/*, rollout_readout,
    phase and phase_names (see harness.outputs.writers); of a policy without attention only step, phase and
    phase_names."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.steps: list[int] = []
        self.attention: list[np.ndarray] = []  # (layers, heads, readouts, keys) float16
        self.rollout: list[np.ndarray] = []  # (readouts, keys) float16
        self.metrics: list[dict[str, np.ndarray]] = []
        self.fractions: list[dict[str, np.ndarray]] = []  # "<obs>/<name>" -> (rows, cols) per step
        self.phases: list[str | None] = []

    def add(self, step: FinishedStep) -> None:
        self.steps.append(step.step)
        self.phases.append(step.record.phase)
        if step.attention is None:  # a policy without attention: step and phase only
            return
        self.attention.append(step.attention.astype(np.float16))
        self.metrics.append(step.metrics)
        self.fractions.append(mask_fractions(step.tokens, step.record.masks))
        if step.rollout is not None:
            self.rollout.append(step.rollout.astype(np.float16))

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        tokens = end.tokens.to_arrays() if end.tokens is not None else {}  # None: the policy gives no attention
        arrays = {"step": np.asarray(self.steps, np.int32), **tokens,
                  **stack_steps(self.metrics, "metrics/"), **stack_steps(self.fractions, "mask_fraction/")}
        if self.attention:
            arrays["readout_attention"] = np.stack(self.attention)
            arrays.update(measure_arrays(arrays, end.tokens))  # per-head measures the report aggregates
        if self.rollout:
            arrays["rollout_readout"] = np.stack(self.rollout)
        names = phase_names_of(self.meta.task, self.phases)
        if names:
            arrays["phase"] = np.asarray([names.index(p) if p in names else -1 for p in self.phases], np.int8)
            arrays["phase_names"] = np.asarray(names)
        write_atomic(self.dir / "attention.npz", lambda f: np.savez(f, **arrays))
        return {"attention": "attention.npz"}


class ActionArrays(Sink):
    """actions.npz: step, predicted, executed, reward, success, inferred, input_hash/<key>."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.steps: list[int] = []
        self.predicted: list[np.ndarray] = []
        self.executed: list[np.ndarray] = []
        self.rewards: list[float] = []
        self.success: list[bool] = []
        self.inferred: list[bool] = []
        self.input_hashes: list[dict[str, int]] = []  # obs key -> input_digest per step

    def add(self, step: FinishedStep) -> None:
        record = step.record
        self.steps.append(step.step)
        self.predicted.append(np.asarray(record.actions_predicted, np.float32))
        self.executed.append(np.asarray(record.action_executed, np.float32))
        self.rewards.append(float(record.reward))
        self.success.append(bool(record.success))
        self.inferred.append(bool(record.inferred))
        self.input_hashes.append({k: input_digest(v) for k, v in (record.policy_inputs or {}).items()})

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        hashes = self.input_hashes
        actions = {
            "step": np.asarray(self.steps, np.int32),
            "predicted": np.stack(self.predicted) if self.predicted else np.zeros((0, 0, 0), np.float32),
            "executed": np.stack(self.executed) if self.executed else np.zeros((0, 0), np.float32),
            "reward": np.asarray(self.rewards, np.float32),
            "success": np.asarray(self.success, bool),
            "inferred": np.asarray(self.inferred, bool),
            **{f"input_hash/{k}": np.asarray([h.get(k, 0) for h in hashes], np.uint64)
               for k in dict.fromkeys(k for h in hashes for k in h)},
        }
        write_atomic(self.dir / "actions.npz", lambda f: np.savez(f, **actions))
        return {"actions": "actions.npz"}


class InputArrays(Sink):
    """inputs.npz (with record_inputs): input/<key> (steps, ...), step, inferred, seed, instruction."""

    @classmethod
    def wanted(cls, options, viewer) -> bool:
        return options.record_inputs

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.steps: list[int] = []
        self.inferred: list[bool] = []
        self.inputs: list[dict[str, np.ndarray]] = []

    def add(self, step: FinishedStep) -> None:
        inputs = step.record.policy_inputs or {}
        if not inputs:
            raise ValueError("record_inputs needs the policy's inputs in every StepRecord (policy_inputs)")
        self.steps.append(step.step)
        self.inferred.append(bool(step.record.inferred))
        self.inputs.append(inputs)

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        recorded = {f"input/{k}": np.stack([entry[k] for entry in self.inputs]) for k in self.inputs[0]} \
            if self.inputs else {}
        recorded.update(step=np.asarray(self.steps, np.int32), inferred=np.asarray(self.inferred, bool),
                        seed=np.asarray(self.meta.seed), instruction=np.asarray(self.meta.instruction))
        write_atomic(self.dir / "inputs.npz", lambda f: np.savez_compressed(f, **recorded))
        return {"inputs": "inputs.npz"}


class MetricLines(Sink):
    """metrics.jsonl: one JSON object per step; every row has the same keys (null where a metric or timing does not
    apply at that step), plus its ids."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.rows: list[tuple[int, float, bool, str | None, dict]] = []  # step, reward, success, phase, metrics

    def add(self, step: FinishedStep) -> None:
        record = step.record
        self.rows.append((step.step, float(record.reward), bool(record.success), record.phase, step.metrics))

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        meta, blocked = self.meta, end.blocked
        names = phase_names_of(meta.task, [phase for _, _, _, phase, _ in self.rows])
        metric_names = list(dict.fromkeys(k for *_, m in self.rows for k in m))
        timing_names = list(dict.fromkeys([k for t in end.timings for k in t] + (["blocked"] if blocked else [])))
        lines = []
        for i, (step, reward, success, phase, metrics) in enumerate(self.rows):
            timings = {**end.timings[i], **({"blocked": blocked[i]} if i < len(blocked) else {})}
            entry = {"run": meta.run, "task": meta.task, "episode": meta.episode, "step": step,
                     "reward": reward, "success": success, **({"phase": phase} if names else {}),
                     **nest({name: metrics.get(name) for name in metric_names}),
                     "timings": {name: timings.get(name) for name in timing_names}}
            lines.append(json.dumps(json_safe(entry)))
        write_lines(self.dir / "metrics.jsonl", lines)
        return {"metrics": "metrics.jsonl"}

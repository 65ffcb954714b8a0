"""Octo checkpoints as a `Policy`: the model (harness/octo) and its batched inference.

`OctoCheckpoint` wraps a loaded `harness.octo.OctoModel`; `BatchInference` is its stateless batched inference: a list
of `InferenceRequest`s -> padded `sample_actions` calls -> one `InferenceResult` each, with readout attention and the
token map, the interventions (harness/interventions.py) and the per-step probes (harness/probes) inside it.

Finetune conventions (Octo's finetuning example: one camera, a `proprio` LowdimObsTokenizer, a new head, window 1):
every low-dimensional key a LowdimObsTokenizer reads is normalised here with the checkpoint's statistics for that key
(`dataset_statistics[dataset_key][key]`, by `proprio_normalization`, as Octo's NormalizeProprio).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from harness.octo.normalization import normalize
from harness.policies.base import AttentionShape, Capabilities, Policy, PolicyFamily
from harness.policy import EnvMismatchError, InferenceRequest, InferenceResult, TaskPrompt
from harness.policy_config import PolicyConfig
from harness.probes.registry import ProbeContext, ProbeItem, active as active_probes

OCTO_CAPABILITIES = Capabilities(attention=True, interventions=True, probes=True, batched=True)


class OctoCheckpoint(Policy):
    """A loaded Octo model (harness.octo.OctoModel) as a Policy; `model` is the Octo model itself."""

    capabilities = OCTO_CAPABILITIES

    def __init__(self, model):
        self.model = model
        self.source = model.source
        self.is_random = bool(model.is_random)
        self.window_size = int(model.window_size)
        self.action_horizon = int(model.action_horizon)
        self.action_dim = int(model.action_dim)
        self.image_sizes = dict(model.image_sizes)
        self.lowdim_sizes = dict(getattr(model, "lowdim_sizes", None) or {})
        self.goal_image_sizes = dict(model.goal_image_sizes)
        self.takes_language = model.config.language is not None
        self.dataset_statistics = getattr(model, "dataset_statistics", None) or {}
        self.example_batch = getattr(model, "example_batch", None)
        self.checkpoint_dir = getattr(model, "checkpoint_dir", None)
        self.text_tokenizer = getattr(model, "text_tokenizer", None)
        transformer = model.config.transformer
        self.attention_shape = AttentionShape(int(transformer.num_layers), int(transformer.num_heads))

    def inference(self, config: PolicyConfig) -> "BatchInference":
        return BatchInference(self.model, config)

    def token_map(self, *args, **kwargs):
        return self.model.token_map(*args, **kwargs)

    @property
    def sample_cache_size(self) -> int:
        return self.model.sample_cache_size


def default_dataset_key(model) -> str | None:
    """The unnormalisation key used when none is given: 'bridge_dataset' if present, else the only key, else None."""
    keys = sorted(getattr(model, "dataset_statistics", {}) or {})
    if not keys:
        return None
    if "bridge_dataset" in keys:
        return "bridge_dataset"
    if len(keys) == 1:
        return keys[0]
    raise ValueError(f"the model has several dataset statistics ({', '.join(keys[:8])}...); choose one with --dataset-key")




def make_task(model, spec: TaskPrompt) -> dict:
    """Octo task dict with batch 1 (language encoded here, once per distinct task)."""
    texts = [spec.instruction] if model.config.language is not None else None  # a model taking both gets both
    goals = {k: v[None] for k, v in spec.goals.items()} if spec.goals is not None else None
    return model.create_task(texts=texts, goals=goals)


def step_key(seed: int, step: int) -> np.ndarray:
    """(2,) uint32 rng key of an episode's inference at control step `step`: fold_in(PRNGKey(seed), step)."""
    return np.asarray(jax.random.fold_in(jax.random.PRNGKey(seed), step))


class BatchInference:
    """Stateless batched inference: requests from many episodes -> `sample_actions` calls -> one result each.

    Every call has exactly `config.inference_batch` examples (padded by repeating the first request, whose
    copies are discarded; more requests are split into several calls), so one shape is compiled, at
    `warm_up()`, and an example's actions and attention are bit-identical whatever shares its call: XLA's
    numbers depend on the batch shape, not on the other examples. Each example also has its own rng key
    (`step_key`). Tasks are built once per distinct TaskPrompt and kept.
    """

    def __init__(self, model, config: PolicyConfig):
        self.model = model
        self.config = config
        self.batch_size = int(config.inference_batch)
        self.dataset_key = config.dataset_key if config.dataset_key is not None else default_dataset_key(model)
        self.statistics = model.unnormalization_statistics(self.dataset_key) if self.dataset_key else None
        self.lowdim_statistics = lowdim_statistics(model, self.dataset_key, config.proprio_normalization)
        # the dimension of the actions handed to the env: the statistics' (Octo keeps those), else the head's
        dims = [len(self.statistics[k]) for k in ("mask", "mean", "p01") if self.statistics and k in self.statistics]
        self.action_dim = dims[0] if dims else int(model.action_dim)
        self._tasks: dict[tuple, dict] = {}  # TaskPrompt.key -> batch-1 task (one per distinct instruction/goals)
        self.intervener = None  # closed-loop intervention (harness/interventions.py), checked against the model here
        self._model = model
        if config.intervention is not None:
            from harness.interventions import Intervener, parse_intervention

            self.intervener = Intervener(model, parse_intervention(config.intervention))
            self._model = self.intervener.model_for_inference()
        # the per-step probes the config turns on (harness.probes), in the registry's order, on the model inferred with
        self.context = ProbeContext(self._model, config, self._inputs, self._sample, self.batch_size, {})
        self.probes = [cls(self.context) for cls in active_probes(config)]

    def probe(self, name: str):
        """The running probe of that name (harness.probes), made for this model; KeyError when it is off."""
        for probe in self.probes:
            if probe.name == name:
                return probe
        raise KeyError(f"probe {name!r} is not on in this PolicyConfig")

    def task(self, spec: TaskPrompt) -> dict:
        if spec.key not in self._tasks:
            self._tasks[spec.key] = make_task(self.model, spec)
        return self._tasks[spec.key]

    def warm_up(self, request: InferenceRequest) -> None:
        """Compile the one batch shape (and build the request's task) with copies of `request`."""
        self([request])

    def __call__(self, requests: list[InferenceRequest]) -> list[InferenceResult]:
        out: list[InferenceResult] = []
        for i in range(0, len(requests), self.batch_size):
            out.extend(self._call(requests[i:i + self.batch_size]))
        return out

    def _inputs(self, requests: list[InferenceRequest]) -> tuple[dict, dict, np.ndarray]:
        """(observations, tasks, keys) of a list of requests: leaves (batch, window, ...), low-dim normalised."""
        stack = lambda *xs: np.stack(xs)  # noqa: E731
        observations = jax.tree.map(stack, *[r.observation for r in requests])  # leaves (batch, window, ...)
        for key, stats in self.lowdim_statistics.items():  # (batch, window, dims), as Octo's NormalizeProprio
            observations[key] = normalize(observations[key], stats, self.config.proprio_normalization, key)
        tasks = jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]), *[self.task(r.task) for r in requests])
        keys = np.stack([step_key(r.seed, r.step) for r in requests])  # (batch, 2) uint32
        return observations, tasks, keys

    def _intervene(self, request: InferenceRequest) -> tuple[InferenceRequest, dict | None]:
        """The request with its current frames masked by the intervention, and those frames (None: unchanged)."""
        if self.intervener is None or not self.intervener.intervention.masks:
            return request, None
        observations, tasks, keys = self._inputs([request])
        frames = self.intervener.mask(observations, tasks, request.seed, request.step, keys[0])
        observation = dict(request.observation)
        for key, frame in frames.items():
            window = np.array(observation[key])
            window[-1] = frame
            observation[key] = window
        return dataclasses.replace(request, observation=observation), frames

    def _call(self, requests: list[InferenceRequest]) -> list[InferenceResult]:
        n = len(requests)
        changed = [self._intervene(r) for r in requests]
        requests = [r for r, _ in changed]
        padded = requests + [requests[0]] * (self.batch_size - n)
        observations, tasks, keys = self._inputs(padded)
        start = time.perf_counter()
        actions, attention = self._sample(observations, tasks, keys)
        chunks = np.asarray(actions, dtype=np.float32)  # (batch, horizon, action_dim)
        readout = np.asarray(attention.readout, dtype=np.float32)  # (batch, layers, heads, readouts, keys)
        full = None if attention.full is None else np.asarray(attention.full, dtype=np.float32)
        elapsed = time.perf_counter() - start
        payloads: list[dict] = [{} for _ in range(n)]
        for probe in self.probes:  # open loop on what the policy saw, after the call: actions never change
            due = [i for i, r in enumerate(requests) if r.step % probe.period == 0]
            if due:
                batch = [ProbeItem(requests[i], chunks[i], readout[i]) for i in due]
                for i, payload in zip(due, probe.run(batch, self.context)):
                    if payload is not None:
                        payloads[i][probe.name] = payload
        return [InferenceResult(chunks[i], readout[i], None if full is None else full[i], elapsed, attention.tokens,
                                changed[i][1], payloads[i]) for i in range(n)]

    def _sample(self, observations: dict, tasks: dict, keys: np.ndarray):
        """(actions, attention) of one compiled call on inputs of the batch shape (`_inputs`)."""
        return self._model.sample_actions(observations, tasks, keys, self.statistics,
                                          full_attention=self.config.full_attention,
                                          normalization_type=self.config.action_normalization,
                                          sampler=self.config.sampler)




def lowdim_statistics(model, dataset_key: str | None, kind: str) -> dict[str, dict | None]:
    """{low-dim obs key: its statistics in dataset_statistics[dataset_key]} for every key the model reads.

    kind "none" needs no statistics (values {key: None}); otherwise a missing entry is a one-line error.
    """
    sizes = getattr(model, "lowdim_sizes", None) or {}
    if kind == "none":
        return {k: None for k in sizes}
    out = {}
    for key in sizes:
        stats = (getattr(model, "dataset_statistics", None) or {}).get(dataset_key or "", {}).get(key)
        if stats is None:
            where = f"dataset_statistics[{dataset_key!r}]" if dataset_key else "dataset_statistics.json (it has no datasets)"
            raise EnvMismatchError(f"the model reads low-dim input {key!r} but {where} has no {key!r} statistics to "
                                   f"normalise it; choose --dataset-key with them, or proprio_normalization='none' "
                                   f"if the model was trained on raw values")
        out[key] = {k: np.asarray(v) for k, v in stats.items() if k in ("mean", "std", "p01", "p99", "mask")}
    return out




class OctoFamily(PolicyFamily):
    """Octo checkpoints: a local folder, hf://owner/name, random:<preset or config>."""

    name = "octo"
    description = "Octo checkpoints (a folder, hf://, random:)"

    def accepts(self, source: str) -> bool:
        return not source.startswith(("ws://", "wss://"))

    def fingerprint(self, source: str, text_tokenizer: str | None = None, **_) -> tuple[str, dict]:
        from harness.policies.fingerprint import model_fingerprint

        return model_fingerprint(source, text_tokenizer)

    def load(self, source: str, text_tokenizer: str | None = None, **_) -> OctoCheckpoint:
        from harness.octo import load_pretrained

        return OctoCheckpoint(load_pretrained(source, text_tokenizer=text_tokenizer))

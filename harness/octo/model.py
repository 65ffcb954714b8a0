"""The Octo policy object: build tasks, sample actions and return the transformer's attention from the
same jitted call (construct it with `harness.octo.load_pretrained`, in loading.py).

    model = load_pretrained("hf://rail-berkeley/octo-small-1.5")       # or a local folder, or random:<preset>
    task = model.create_task(texts=["pick up the cube"])                # T5 runs here, once per task
    actions, attention = model.sample_actions(observations, task, jax.random.PRNGKey(0),
                                              model.unnormalization_statistics("bridge_dataset"))

`observations` follow Octo: `image_<cam>` (batch, window, H, W, 3) uint8 at `model.image_sizes`,
`timestep_pad_mask` (batch, window) bool, optional `pad_mask_dict` {image_<cam>: (batch, window)} and
low-dim keys (e.g. `proprio`) if the model tokenizes them.
`attention.readout` (batch, layers, heads, readouts, keys) holds the post-softmax attention rows of the
last timestep's readout tokens over every key; `attention.tokens` says what each key is.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from harness.octo import presets
from harness.octo.config import DiffusionHeadConfig, ImageTokenizerConfig, OctoConfig
from harness.octo.diffusion import SAMPLERS, make_schedule, sample
from harness.octo.errors import InputError, OctoError, UnknownDatasetKeyError
from harness.octo.heads import ContinuousHead, ScoreNetwork, pool_readouts
from harness.octo.network import NON_DATA_KEYS, LanguageTokenizer, OctoTransformer, sequence_layout
from harness.octo.stem import image_stack_keys, lowdim_stack_keys
from harness.octo.tokens import TokenMap

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Attention:
    """Attention captured during one `sample_actions` call."""

    readout: jax.Array  # (batch, layers, heads, readouts, keys) float32, last timestep's readout rows
    full: jax.Array | None  # (batch, layers, heads, queries, keys) float32 when full_attention=True
    tokens: TokenMap  # what each key is (group, timestep, patch row/col)


class OctoModel:
    """A loaded Octo policy. Build with `load_pretrained`; read-only after construction."""

    def __init__(self, *, config: OctoConfig, params: dict, example_batch: dict, dataset_statistics: dict,
                 text_tokenizer, t5_config, source: str, is_random: bool, checkpoint_dir=None):
        self.config = config
        self.params = params
        self.example_batch = example_batch
        self.dataset_statistics = dataset_statistics
        self.text_tokenizer = text_tokenizer
        self.t5_config = t5_config
        self.source = source
        self.is_random = is_random
        self.checkpoint_dir = checkpoint_dir  # local folder the model was read from (None: random preset)
        self.image_sizes, self.window_size = example_observation_sizes(example_batch["observation"], config.window_size)
        self.lowdim_sizes = example_lowdim_sizes(config, example_batch["observation"])  # obs key -> dims
        self.goal_image_sizes = {k: tuple(int(s) for s in np.shape(v)[1:3]) for k, v in example_batch.get("task", {}).items()
                                 if k.startswith("image_") and np.ndim(v) == 4}
        head = config.action_head
        self.action_horizon = head.action_horizon
        self.action_dim = head.action_dim
        self._schedule = make_schedule(head.diffusion_steps) if isinstance(head, DiffusionHeadConfig) else None
        self._sample_jit = jax.jit(self._sample, static_argnames=("capture", "normalization_type", "sampler"))
        self._encode_jit = jax.jit(self._encode)
        self._transformer_jit = jax.jit(self._transformer, static_argnames=("intermediates",))
        backbone = {k: v for k, v in params["octo_transformer"].items() if not k.startswith("task_tokenizers_")}
        self._inference_params = {**params, "octo_transformer": backbone}  # without the T5 encoder, built once
        self._token_maps: dict = {}  # SequenceLayout -> TokenMap

    # ------------------------------------------------------------------ statistics

    def unnormalization_statistics(self, dataset_key: str | None) -> dict | None:
        """Action statistics {mean, std, p01, p99, mask, ...} of a dataset; None -> None (normalised actions)."""
        if dataset_key is None:
            return None
        if dataset_key not in self.dataset_statistics:
            available = sorted(self.dataset_statistics) or "none (this model has no dataset statistics)"
            raise UnknownDatasetKeyError(f"unknown dataset key {dataset_key!r}; available: {available}")
        stats = self.dataset_statistics[dataset_key]
        return dict(stats["action"]) if "action" in stats else dict(stats)

    # ------------------------------------------------------------------ tasks

    def create_task(self, texts: Sequence[str] | None = None, goals: Mapping[str, np.ndarray] | None = None) -> dict:
        """Octo task dict for a batch of instructions and/or goal images, with the language encoded once.

        Missing goal images are zeros with pad_mask False (as Octo's create_tasks). The T5 encoding is
        stored under "language_encoding" (batch, tokens, d_model) and reused by `sample_actions`.
        """
        if texts is None and goals is None:
            raise InputError("create_task needs texts=[...] or goals={'image_primary': ...}")
        if texts is not None and isinstance(texts, str):
            texts = [texts]
        goals = dict(goals or {})
        unknown = sorted(set(goals) - set(self.goal_image_sizes))
        if unknown:
            raise InputError(f"unknown goal key(s) {unknown}; this model takes goals {sorted(self.goal_image_sizes)}")
        batch = len(texts) if texts is not None else int(np.shape(next(iter(goals.values())))[0])
        task: dict[str, Any] = {"pad_mask_dict": {}}
        for key, (h, w) in self.goal_image_sizes.items():
            if key in goals:
                img = np.asarray(goals[key])
                if img.shape != (batch, h, w, 3) or img.dtype != np.uint8:
                    raise InputError(f"goals[{key!r}] is {img.shape} {img.dtype}; expected ({batch}, {h}, {w}, 3) uint8")
                task[key] = img
            else:
                task[key] = np.zeros((batch, h, w, 3), np.uint8)
            task["pad_mask_dict"][key] = np.full((batch,), key in goals)
        if self.config.language is not None:
            words = list(texts) if texts is not None else [""] * batch
            encoded = self.text_tokenizer.encode(words)
            task["language_instruction"] = {k: np.asarray(v, np.int32) for k, v in encoded.items()}
            task["pad_mask_dict"]["language_instruction"] = np.full((batch,), texts is not None)
            task["language_encoding"] = self.encode_language(task["language_instruction"])
        elif texts is not None:
            raise InputError("this model is goal-conditioned (no language tokenizer); pass goals= instead of texts=")
        return task

    def encode_language(self, language_instruction: Mapping[str, np.ndarray]) -> jax.Array:
        """T5 encoding (batch, tokens, d_model) of {input_ids, attention_mask} (batch, tokens) int32."""
        ids = jnp.asarray(language_instruction["input_ids"], jnp.int32)
        mask = jnp.asarray(language_instruction["attention_mask"], jnp.int32)
        return self._encode_jit(self.params["octo_transformer"][f"task_tokenizers_{self.config.language.name}"], ids, mask)

    def _encode(self, params, ids, mask):
        return LanguageTokenizer(self.t5_config).apply({"params": params}, ids, mask)

    # ------------------------------------------------------------------ inference

    def sample_actions(self, observations: Mapping, task: Mapping, rng: jax.Array,
                       unnormalization_statistics: Mapping | None = None, *, full_attention: bool = False,
                       normalization_type: str = "normal", capture_attention: bool = True,
                       sampler: str = "latest") -> tuple[jax.Array, Attention | None]:
        """Sample an action chunk (batch, action_horizon, action_dim) and capture attention.

        rng: one key (2,) uint32 for the whole batch (Octo's behaviour: an example's noise depends on its
        batch position), or one key per example (batch, 2) uint32: example i then gets what a batch-1 call
        with key i gives (up to float rounding), whatever else shares the batch.
        Actions are normalised when `unnormalization_statistics` is None, else unnormalised with
        normalization_type "normal" (a*std+mean) or "bounds" (from p01/p99), honouring the statistics'
        mask. One jitted function; it compiles once per input structure and shape (and per option).
        capture_attention=False returns (actions, None) and skips copying attention out (for
        measuring what capture costs). sampler (diffusion heads): "latest" samples as the latest original
        code does with any checkpoint (1.0-format ones included); "v0.1.0" as the December 2023 code
        did (one more rng split, no action mask); see harness.octo.diffusion.
        """
        if normalization_type not in ("normal", "bounds"):
            raise InputError(f"normalization_type must be 'normal' or 'bounds', got {normalization_type!r}")
        if sampler not in SAMPLERS:
            raise InputError(f"sampler must be one of {', '.join(SAMPLERS)}, got {sampler!r}")
        obs, pad = self._prepare_observations(observations)
        task_in, encoding = self._prepare_task(task, pad.shape[0])
        stats = _prepare_statistics(unnormalization_statistics, normalization_type, self.action_dim)
        rng = jnp.asarray(rng)
        if rng.shape not in ((2,), (pad.shape[0], 2)):
            raise InputError(f"rng is {rng.shape}; expected one key (2,) or one key per example ({pad.shape[0]}, 2)")
        layout = self._layout(obs, encoding)
        capture = "full" if full_attention else ("readout" if capture_attention else "none")
        compiled = self.sample_cache_size
        start = time.perf_counter()
        actions, captured = self._sample_jit(self._inference_params, obs, task_in, encoding, pad, rng, stats,
                                             capture=capture, normalization_type=normalization_type, sampler=sampler)
        if self.sample_cache_size > compiled:  # this call compiled a new variant
            jax.block_until_ready(actions)
            log.info("sample_actions compiled and ran in %.2f s (batch %d, window %d, %d keys, attention capture: %s)",
                     time.perf_counter() - start, pad.shape[0], pad.shape[1], layout.num_tokens, capture)
        tokens = self._token_map(layout)
        if capture == "none":
            return actions, None
        if full_attention:
            readout = captured[:, :, :, tokens.readout_index, :]
            return actions, Attention(readout=readout, full=captured, tokens=tokens)
        return actions, Attention(readout=captured, full=None, tokens=tokens)

    @property
    def sample_cache_size(self) -> int:
        """Number of compiled variants of the jitted sampler (1 after any number of same-shape calls)."""
        return self._sample_jit._cache_size()

    def _sample(self, params, obs, task, encoding, pad, rng, stats, *, capture, normalization_type, sampler):
        layout = self._layout(obs, encoding)
        rows = {"full": None, "none": (), "readout": tuple(int(i) for i in self._token_map(layout).readout_index)}[capture]
        out = OctoTransformer(self.config, capture_rows=rows).apply({"params": params["octo_transformer"]}, obs, task,
                                                                   encoding, pad)
        actions = self.head_actions(params["heads_action"], out, rng, stats, normalization_type, sampler)
        return actions, (None if capture == "none" else out["attention"])

    def head_actions(self, head_params, out, rng, stats=None, normalization_type="normal", sampler="latest"):
        """The action head on the transformer's output `out` (OctoTransformer's dict) -> (batch, horizon, dim).

        Traceable (jit, grad): the diffusion head samples with `rng` (one key, or one per example), the
        continuous heads read the pooled readouts directly. stats None: normalised actions.
        """
        head = self.config.action_head
        tokens, mask = out["groups"][head.readout_key]
        embedding = pool_readouts(head_params, head, tokens, mask)  # (batch, window, D)
        batch, window = embedding.shape[:2]
        if isinstance(head, DiffusionHeadConfig):
            flat = head.action_horizon * head.action_dim
            # as Octo: dimensions beyond the statistics' (the embodiment's) are masked to training-time noise
            dims = head.action_dim if stats is None else stats["mask"].shape[0]
            action_mask = jnp.broadcast_to(
                jnp.tile(jnp.arange(head.action_dim) < dims, head.action_horizon), (batch, window, flat)
            )
            net = ScoreNetwork(head)

            def score_of(emb):
                def score(x, t):
                    time_in = jnp.broadcast_to(t, (*x.shape[:-1], 1))
                    return net.apply({"params": head_params["diffusion_model"]}, emb, x, time_in)
                return score

            if rng.ndim == 2:  # keys (batch, 2): example i draws exactly what a batch-1 call with key i draws
                one_mask = None if action_mask is None else action_mask[:1]

                def one(key, emb):  # emb (window, D) -> (window, flat)
                    return sample(score_of(emb[None]), key, (1, window, flat), self._schedule, head.max_action,
                                  one_mask, sampler)[0]

                x = jax.vmap(one)(rng, embedding)
            else:
                x = sample(score_of(embedding), rng, (batch, window, flat), self._schedule, head.max_action, action_mask,
                           sampler)
            actions = x.reshape(batch, window, head.action_horizon, head.action_dim)[:, -1]
        else:
            actions = ContinuousHead(head).apply({"params": {"mean_proj": head_params["mean_proj"]}}, embedding)[:, -1]
        if stats is not None:
            actions = _unnormalize(actions, stats, normalization_type)
        return actions

    # ------------------------------------------------------------------ inspection (tests, analysis)

    def token_map(self, observations: Mapping | None = None, task: Mapping | None = None) -> TokenMap:
        """Token map of the sequence for these inputs (default: the example batch's full inputs)."""
        if observations is None:
            obs = {k: v for k, v in self.example_batch["observation"].items() if k in self._used_observation_keys(self.example_batch["observation"])}
        else:
            obs, _ = self._prepare_observations(observations)
        n_lang = None
        if self.config.language is not None and (task is None or "language_instruction" in task or "language_encoding" in task):
            n_lang = self.text_tokenizer.max_length if self.text_tokenizer is not None else presets.LANGUAGE_TOKENS
            if task is not None and "language_encoding" in task:
                n_lang = int(np.shape(task["language_encoding"])[1])
        shapes = {k: np.shape(v) for k, v in obs.items() if k != "pad_mask_dict"}
        return self._token_map(sequence_layout(self.config, shapes, n_lang))

    def run_transformer(self, observations: Mapping, task: Mapping, *, intermediates: bool = False) -> dict:
        """Forward of the backbone with full attention: {"groups", "attention", ...intermediates}. One jitted
        function (compiled once per input shape), not op by op: un-jitted, each of its hundreds of operations
        compiled a program of its own."""
        obs, pad = self._prepare_observations(observations)
        task_in, encoding = self._prepare_task(task, pad.shape[0])
        return self._transformer_jit(self._inference_params["octo_transformer"], obs, task_in, encoding, pad,
                                     intermediates=intermediates)

    def _transformer(self, params, obs, task, encoding, pad, *, intermediates):
        module = OctoTransformer(self.config, capture_rows=None, keep_intermediates=intermediates)
        return module.apply({"params": params}, obs, task, encoding, pad)

    def predict_eps(self, readout_embedding: jax.Array, noisy_actions: jax.Array, time: jax.Array) -> jax.Array:
        """Diffusion score network: (batch, window, D), (batch, window, horizon*dim), (batch, window, 1) -> eps."""
        head = self.config.action_head
        if not isinstance(head, DiffusionHeadConfig):
            raise OctoError("predict_eps needs a diffusion action head")
        return ScoreNetwork(head).apply({"params": self.params["heads_action"]["diffusion_model"]},
                                        readout_embedding, noisy_actions, time)

    # ------------------------------------------------------------------ input preparation

    def _used_observation_keys(self, observations: Mapping) -> list[str]:
        keys = [k for k in observations if k not in NON_DATA_KEYS]
        used = set()
        for tok in self.config.observation_tokenizers:
            if isinstance(tok, ImageTokenizerConfig):
                used.update(image_stack_keys(tok, keys))
            else:
                used.update(lowdim_stack_keys(tok, keys))
        return [k for k in keys if k in used]

    def _prepare_observations(self, observations: Mapping) -> tuple[dict, jax.Array]:
        if not isinstance(observations, Mapping):
            raise InputError("observations must be a dict of arrays (image_*, timestep_pad_mask, ...)")
        keys = self._used_observation_keys(observations)
        if not keys:
            raise InputError(f"observations {sorted(observations)} contain none of the model's inputs {sorted(self.image_sizes)}")
        obs: dict[str, Any] = {}
        batch_window = None
        for k in keys:
            value = observations[k] if isinstance(observations[k], jax.Array) else np.asarray(observations[k])
            if k.startswith("image_"):
                h, w = self.image_sizes.get(k, (None, None))
                if value.ndim != 5 or value.shape[-1] != 3 or value.dtype != np.uint8 or (h is not None and value.shape[2:4] != (h, w)):
                    raise InputError(f"observations[{k!r}] is {value.shape} {value.dtype}; expected (batch, window, {h}, {w}, 3) "
                                     "uint8 (resize frames to model.image_sizes)")
            elif value.ndim != 3:
                raise InputError(f"observations[{k!r}] is {value.shape}; expected (batch, window, dims)")
            else:
                value = jnp.asarray(value, jnp.float32)
            obs[k] = value
            if batch_window is None:
                batch_window = tuple(value.shape[:2])
            elif tuple(value.shape[:2]) != batch_window:
                raise InputError(f"observations[{k!r}] has (batch, window) {value.shape[:2]}, others {batch_window}")
        if batch_window[1] > self.config.max_horizon:
            raise InputError(f"window {batch_window[1]} exceeds the model's max_horizon {self.config.max_horizon}")
        pad = observations.get("timestep_pad_mask", observations.get("pad_mask"))
        pad = jnp.ones(batch_window, bool) if pad is None else jnp.asarray(pad, bool)
        if pad.shape != batch_window:
            raise InputError(f"timestep_pad_mask is {pad.shape}; expected (batch, window) = {batch_window}")
        if "pad_mask_dict" in observations:
            masks = {k: jnp.asarray(v, bool) for k, v in observations["pad_mask_dict"].items() if k in keys}
            if masks:
                obs["pad_mask_dict"] = masks
        return obs, pad

    def _prepare_task(self, task: Mapping, batch: int) -> tuple[dict, jax.Array | None]:
        if not isinstance(task, Mapping):
            raise InputError("task must be a dict from model.create_task(...)")
        task_in: dict[str, Any] = {}
        for k, (h, w) in self.goal_image_sizes.items():
            if k in task:
                value = task[k]
                if np.shape(value) != (batch, h, w, 3) or np.dtype(value.dtype) != np.uint8:
                    raise InputError(f"task[{k!r}] is {np.shape(value)} {value.dtype}; expected ({batch}, {h}, {w}, 3) uint8 "
                                     "(build tasks with model.create_task)")
                task_in[k] = jnp.asarray(value, jnp.uint8)
        encoding = None
        lang = self.config.language
        if lang is not None and ("language_encoding" in task or "language_instruction" in task):
            encoding = task.get("language_encoding")
            if encoding is None:
                encoding = self.encode_language(task["language_instruction"])
            encoding = jnp.asarray(encoding, jnp.float32)
            if encoding.ndim != 3 or encoding.shape[0] != batch:
                raise InputError(f"task language encoding is {encoding.shape}; expected ({batch}, tokens, d_model) "
                                 "(create the task with as many instructions as the observation batch)")
            pad = task.get("pad_mask_dict", {}).get("language_instruction")
            if pad is not None:
                task_in["pad_mask_dict"] = {"language_instruction": jnp.asarray(pad, bool)}
        return task_in, encoding

    def _token_map(self, layout) -> TokenMap:
        """Token map of a layout, built once and shared read-only (its arrays are not writeable)."""
        if layout not in self._token_maps:
            tokens = layout.token_map()
            for arr in (tokens.group, tokens.timestep, tokens.row, tokens.col, tokens.readout_index):
                arr.flags.writeable = False
            self._token_maps[layout] = tokens
        return self._token_maps[layout]

    def _layout(self, obs: Mapping, encoding):
        shapes = {k: np.shape(v) for k, v in obs.items() if k != "pad_mask_dict"}
        return sequence_layout(self.config, shapes, None if encoding is None else int(encoding.shape[1]))


def example_lowdim_sizes(config: OctoConfig, obs: Mapping) -> dict[str, int]:
    """{observation key: dims} of every low-dim key a LowdimObsTokenizer reads, from an example observation dict."""
    keys = [k for k in obs if k not in NON_DATA_KEYS]
    sizes = {}
    for tok in config.observation_tokenizers:
        if not isinstance(tok, ImageTokenizerConfig):
            for k in lowdim_stack_keys(tok, keys):
                sizes[k] = int(np.shape(obs[k])[-1])
    return sizes


def example_observation_sizes(obs: Mapping, default_window: int) -> tuple[dict[str, tuple[int, int]], int]:
    """An example batch's observation dict -> ({image key: (height, width)}, window)."""
    sizes = {k: tuple(int(s) for s in np.shape(v)[2:4]) for k, v in obs.items() if k.startswith("image_") and np.ndim(v) == 5}
    window = int(np.shape(obs["timestep_pad_mask"])[1]) if "timestep_pad_mask" in obs else default_window
    return sizes, window


def _prepare_statistics(stats: Mapping | None, normalization_type: str, action_dim: int) -> dict | None:
    """Action statistics as float32/bool arrays in a fixed structure, or None."""
    if stats is None:
        return None
    if "action" in stats and isinstance(stats["action"], Mapping):
        stats = stats["action"]
    needed = ("mean", "std") if normalization_type == "normal" else ("p01", "p99")
    missing = [k for k in needed if k not in stats]
    if missing:
        raise InputError(f"unnormalization statistics lack {missing} needed for normalization_type={normalization_type!r}")
    a, b = (np.asarray(stats[k], np.float32) for k in needed)
    mask = np.asarray(stats.get("mask", np.ones(a.shape, bool)), bool)
    if a.shape != b.shape or mask.shape != a.shape or a.ndim != 1 or a.shape[0] > action_dim:
        raise InputError(f"unnormalization statistics have shapes {a.shape}/{b.shape}/mask {mask.shape}; expected ({action_dim},)")
    return {"a": jnp.asarray(a), "b": jnp.asarray(b), "mask": jnp.asarray(mask)}


def _unnormalize(actions: jax.Array, stats: dict, normalization_type: str) -> jax.Array:
    """As Octo: keep the statistics' dims, then mean/std or p01/p99 scaling where mask is True."""
    actions = actions[..., : stats["mask"].shape[0]]
    if normalization_type == "normal":  # a = mean, b = std
        scaled = actions * stats["b"] + stats["a"]
    else:  # a = p01, b = p99
        scaled = (actions + 1) * (stats["b"] - stats["a"]) / 2 + stats["a"]
    return jnp.where(stats["mask"], scaled, actions)

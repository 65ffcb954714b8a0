"""Octo's transformer backbone: tokenize, assemble the block sequence, run it, split the outputs.

`OctoTransformer` is the `octo_transformer` parameter scope of Octo's checkpoints (minus the T5 weights
under `task_tokenizers_language/hf_model`, which `LanguageTokenizer` applies separately so a task's
language encoding can be computed once and reused across control steps).

Sequence (Octo's OctoTransformer + BlockTransformer):
  prefix:         task_<name>         = Dense(T5 encoding) + pos_embedding (1, 16, D)
  per timestep t: obs_<tokenizer>     = Dense(stem tokens) + pos_embedding[:, t] (1, max_horizon, n, D)
                  obs_task_<name>     = the prefix tokens again (repeat_task_tokens)
                  readout_<name>      = pos_embedding[:, t]
Key validity: task tokens follow `task["pad_mask_dict"][<name>_instruction]`; obs tokens
`timestep_pad_mask AND pad_mask_dict[key]`; repeated task tokens the task mask (not the timestep
mask); readouts always valid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from harness.octo.config import ImageTokenizerConfig, LanguageTokenizerConfig, OctoConfig
from harness.octo.stem import ImageTokenizer, image_stack_keys, lowdim_stack_keys, lowdim_tokens
from harness.octo.tokens import TokenMap, build_token_map
from harness.octo.transformer import BlockTransformer, attention_rule_mask

_pos_init = nn.initializers.normal(stddev=0.02)


@dataclass(frozen=True)
class SequenceLayout:
    """Which token groups a given input structure produces, and how many tokens each has."""

    prefix_groups: tuple[tuple[str, int], ...]  # (group, tokens)
    timestep_groups: tuple[tuple[str, int], ...]
    window: int
    image_groups: tuple[tuple[str, str, int, int], ...]  # (group, observation key, rows, cols)

    @property
    def num_tokens(self) -> int:
        return sum(n for _, n in self.prefix_groups) + self.window * sum(n for _, n in self.timestep_groups)

    def token_map(self) -> TokenMap:
        return build_token_map(list(self.prefix_groups), list(self.timestep_groups), self.window, self.image_groups)


NON_DATA_KEYS = ("pad_mask_dict", "timestep_pad_mask", "pad_mask")  # observation keys that are masks, not model inputs


def sequence_layout(config: OctoConfig, observation_shapes: Mapping[str, tuple[int, ...]],
                    language_tokens: int | None) -> SequenceLayout:
    """Layout for observations of the given shapes `{key: (batch, window, ...)}`.

    language_tokens: number of language tokens, or None when the task has no language (Octo then
    skips the language tokenizer).
    """
    keys = [k for k in observation_shapes if k not in NON_DATA_KEYS]
    window = int(next(iter(observation_shapes[k] for k in keys))[1])
    prefix, timestep, images = [], [], []
    for tok in config.task_tokenizers:
        if language_tokens is not None:
            prefix.append((f"task_{tok.name}", int(language_tokens)))
    for tok in config.observation_tokenizers:
        group = f"obs_{tok.name}"
        if isinstance(tok, ImageTokenizerConfig):
            stack = image_stack_keys(tok, keys)
            if not stack:
                continue
            h, w = observation_shapes[stack[0]][2:4]
            rows, cols = tok.encoder.grid(int(h), int(w))
            timestep.append((group, rows * cols))
            images.append((group, stack[0], rows, cols))
        else:
            stack = lowdim_stack_keys(tok, keys)
            if not stack:
                continue
            timestep.append((group, sum(int(observation_shapes[k][-1]) for k in stack)))
    if config.repeat_task_tokens:
        timestep.extend((f"obs_{name}", n) for name, n in prefix)
    timestep.extend((f"readout_{name}", n) for name, n in config.readouts)
    return SequenceLayout(tuple(prefix), tuple(timestep), window, tuple(images))


class LanguageTokenizer(nn.Module):
    """The `task_tokenizers_<name>` scope: a T5 encoder named `hf_model`."""

    t5_config: object  # harness.octo.t5.T5Config

    @nn.compact
    def __call__(self, input_ids: jax.Array, attention_mask: jax.Array) -> jax.Array:
        from harness.octo.t5 import T5Encoder

        return T5Encoder(self.t5_config, name="hf_model")(input_ids, attention_mask)  # (batch, tokens, d_model)


class OctoTransformer(nn.Module):
    """Observations + task (with precomputed language encoding) -> token groups and attention.

    capture_rows: key positions whose attention rows are returned (None = full matrices).
    Returns a dict with "groups" {name: (tokens, mask)}, "attention" (batch, layers, heads, rows, keys)
    and, with keep_intermediates, the tokenizer outputs, the assembled input, the mask and layer outputs.
    """

    config: OctoConfig
    capture_rows: tuple[int, ...] | None = None
    keep_intermediates: bool = False

    def _pos_embedding(self, name: str, tokens: jax.Array) -> jax.Array:
        if tokens.ndim == 3:  # prefix (batch, n, D)
            emb = self.param(f"{name}_pos_embedding", _pos_init, (1, *tokens.shape[-2:]))
        else:  # timesteps (batch, window, n, D): one embedding per timestep up to max_horizon
            emb = self.param(f"{name}_pos_embedding", _pos_init, (1, self.config.max_horizon, *tokens.shape[-2:]))
            emb = emb[:, : tokens.shape[1]]
        return jnp.broadcast_to(emb, tokens.shape)

    @nn.compact
    def __call__(self, observations: Mapping[str, jax.Array], task: Mapping[str, jax.Array],
                 language_encoding: jax.Array | None, timestep_pad_mask: jax.Array):
        cfg = self.config
        d = cfg.token_embedding_size
        obs_keys = [k for k in observations if k != "pad_mask_dict"]
        batch, window = observations[obs_keys[0]].shape[:2]
        shapes = {k: observations[k].shape for k in obs_keys}
        layout = sequence_layout(cfg, shapes, None if language_encoding is None else language_encoding.shape[1])
        extras: dict = {"tokenizer": {}}

        prefix: list[tuple[str, jax.Array, jax.Array]] = []  # (group, (b, n, D), (b, n) bool)
        for tok in cfg.task_tokenizers:
            if language_encoding is None:
                continue
            group = f"task_{tok.name}"
            tokens = nn.Dense(d, name=f"{group}_projection")(language_encoding)
            tokens = tokens + self._pos_embedding(group, tokens)
            mask = _task_mask(tok, task, tokens.shape[:-1])
            extras["tokenizer"][group] = (language_encoding, mask)
            prefix.append((group, tokens, mask))

        steps: list[tuple[str, jax.Array, jax.Array]] = []  # (group, (b, t, n, D), (b, t, n) bool)
        for tok in cfg.observation_tokenizers:
            group = f"obs_{tok.name}"
            if isinstance(tok, ImageTokenizerConfig):
                if not image_stack_keys(tok, obs_keys):
                    continue
                raw, mask = ImageTokenizer(tok, name=f"observation_tokenizers_{tok.name}")(observations, task)
            else:
                if not lowdim_stack_keys(tok, obs_keys):
                    continue
                raw, mask = lowdim_tokens(tok, observations)
            extras["tokenizer"][group] = (raw, mask)
            tokens = nn.Dense(d, name=f"{group}_projection")(raw)
            tokens = tokens + self._pos_embedding(group, tokens)
            steps.append((group, tokens, jnp.logical_and(timestep_pad_mask[:, :, None], mask)))
        if cfg.repeat_task_tokens:
            for group, tokens, mask in list(prefix):
                steps.append((
                    f"obs_{group}",
                    jnp.tile(tokens[:, None], (1, window, 1, 1)),
                    jnp.tile(mask[:, None], (1, window, 1)),
                ))
        for name, n in cfg.readouts:
            group = f"readout_{name}"
            tokens = jnp.zeros((batch, window, n, d), jnp.float32)
            tokens = tokens + self._pos_embedding(group, tokens)
            steps.append((group, tokens, jnp.ones((batch, window, n), dtype=bool)))
        assert [g for g, _ in layout.prefix_groups] == [g for g, _, _ in prefix]
        assert [g for g, _ in layout.timestep_groups] == [g for g, _, _ in steps]

        # assemble (batch, N, D): prefix tokens, then timestep-major blocks of all timestep groups
        seq_steps = jnp.concatenate([t for _, t, _ in steps], axis=2).reshape(batch, -1, d)
        valid_steps = jnp.concatenate([m for _, _, m in steps], axis=2).reshape(batch, -1)
        if prefix:
            seq = jnp.concatenate([jnp.concatenate([t for _, t, _ in prefix], axis=1), seq_steps], axis=1)
            valid = jnp.concatenate([jnp.concatenate([m for _, _, m in prefix], axis=1), valid_steps], axis=1)
        else:
            seq, valid = seq_steps, valid_steps
        rules = attention_rule_mask(layout.prefix_groups, layout.timestep_groups, window, cfg.use_correct_attention)
        encoded, attention, layer_outputs, full_mask = BlockTransformer(
            cfg.transformer, self.capture_rows, self.keep_intermediates, name="BlockTransformer_0"
        )(seq, valid, rules)

        groups = _split(encoded, prefix, steps, window)
        out = {"groups": groups, "attention": attention}
        if self.keep_intermediates:
            out.update(extras, input_tokens=seq, attention_mask=full_mask, layer_outputs=layer_outputs,
                       final_output=encoded)
        return out


def _task_mask(tok: LanguageTokenizerConfig, task: Mapping, shape: tuple[int, ...]) -> jax.Array:
    pad = task.get("pad_mask_dict") if task is not None else None
    key = "language_instruction"
    if not tok.proper_pad_mask or pad is None or key not in pad:
        return jnp.ones(shape, dtype=bool)
    return jnp.broadcast_to(jnp.asarray(pad[key], bool)[:, None], shape)


def _split(encoded: jax.Array, prefix: Sequence, steps: Sequence, window: int) -> dict:
    """Encoded sequence -> {group: (tokens, mask)} plus Octo's concatenations "task" and "obs"."""
    batch, _, d = encoded.shape
    groups = {}
    n_prefix = sum(t.shape[1] for _, t, _ in prefix)
    start = 0
    for name, t, m in prefix:
        groups[name] = (encoded[:, start : start + t.shape[1]], m)
        start += t.shape[1]
    blocks = encoded[:, n_prefix:].reshape(batch, window, -1, d)
    start = 0
    for name, t, m in steps:
        n = t.shape[2]
        groups[name] = (blocks[:, :, start : start + n], m)
        start += n
    if prefix:
        groups["task"] = (
            jnp.concatenate([groups[n][0] for n, _, _ in prefix], axis=1),
            jnp.concatenate([groups[n][1] for n, _, _ in prefix], axis=1),
        )
    obs = [n for n, _, _ in steps if n.startswith("obs_")]
    if obs:
        groups["obs"] = (
            jnp.concatenate([groups[n][0] for n in obs], axis=-2),
            jnp.concatenate([groups[n][1] for n in obs], axis=-1),
        )
    return groups


def example_inputs(config: OctoConfig, image_sizes: Mapping[str, tuple[int, int]], window: int,
                   lowdim_sizes: Mapping[str, int] | None = None, language_tokens: int = 16,
                   d_model: int | None = None, batch: int = 1):
    """Zero inputs of the right structure for `OctoTransformer.init` (observations, task, encoding, pad)."""
    obs = {k: jnp.zeros((batch, window, h, w, 3), jnp.uint8) for k, (h, w) in image_sizes.items()}
    for k, n in (lowdim_sizes or {}).items():
        obs[k] = jnp.zeros((batch, window, n), jnp.float32)
    task = {k: jnp.zeros((batch, h, w, 3), jnp.uint8) for k, (h, w) in image_sizes.items()}
    encoding = None
    if config.language is not None and d_model is not None:
        encoding = jnp.zeros((batch, language_tokens, d_model), jnp.float32)
        task["pad_mask_dict"] = {"language_instruction": jnp.ones((batch,), bool)}
    return obs, task, encoding, jnp.ones((batch, window), bool)


def init_params(rng: jax.Array, config: OctoConfig, image_sizes: Mapping[str, tuple[int, int]], window: int,
                t5_config=None, lowdim_sizes: Mapping[str, int] | None = None, language_tokens: int = 16) -> dict:
    """Fresh parameters laid out exactly as an Octo checkpoint (`octo_transformer`, `heads_<name>`).

    Under `jax.eval_shape` this gives the expected parameter tree without computing anything.
    """
    from harness.octo.heads import init_head_params

    k_backbone, k_language, k_heads = jax.random.split(rng, 3)
    d_model = t5_config.d_model if t5_config is not None else None
    obs, task, encoding, pad = example_inputs(config, image_sizes, window, lowdim_sizes, language_tokens, d_model)
    backbone = dict(OctoTransformer(config, capture_rows=()).init(k_backbone, obs, task, encoding, pad)["params"])
    if config.language is not None:
        if t5_config is None:
            raise ValueError("a language-conditioned config needs its T5 config")
        ids = jnp.ones((1, language_tokens), jnp.int32)
        backbone[f"task_tokenizers_{config.language.name}"] = dict(
            LanguageTokenizer(t5_config).init(k_language, ids, ids)["params"]
        )
    params = {"octo_transformer": backbone}
    readouts = dict(config.readouts)
    for (name, head), key in zip(config.heads, jax.random.split(k_heads, len(config.heads))):
        n_readout = readouts.get(head.readout_key.removeprefix("readout_"), 1)
        params[f"heads_{name}"] = init_head_params(key, head, config.token_embedding_size, n_readout)
    return params


def random_params(shapes: Mapping, seed: int = 0) -> dict:
    """Deterministic random parameters for a tree of shapes, without running the network.

    Initialising through `init` means tracing and compiling a forward pass (about 20 s for octo-small
    on a laptop CPU); drawing each leaf directly from numpy takes a second or two. Each leaf's stream
    depends only on `seed` and its path. Scheme (close to the modules' own initialisers):
    kernels N(0, 1/fan_in), biases 0, norm scales 1, position embeddings N(0, 0.02), embedding tables
    N(0, 1), Fourier features N(0, 0.2), MAP probes N(0, 1/D).
    """
    import zlib

    from flax import traverse_util

    out = {}
    for path, leaf in traverse_util.flatten_dict(dict(shapes)).items():
        shape, name, parent = tuple(leaf.shape), path[-1], path[-2] if len(path) > 1 else ""
        rng = np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32("/".join(path).encode())]))
        if name in ("bias",):
            value = np.zeros(shape, np.float32)
        elif name in ("scale", "weight"):  # LayerNorm/GroupNorm scale, T5 RMS-norm weight
            value = np.ones(shape, np.float32)
        else:
            if name.endswith("pos_embedding"):
                std = 0.02
            elif name == "embedding":
                std = 1.0
            elif parent == "time_preprocess":
                std = 0.2
            elif name == "probe":
                std = shape[-1] ** -0.5
            else:  # kernels: (in..., out) or attention projections (D, heads, head_dim)
                fan_in = shape[0] if parent in ("query", "key", "value") or len(shape) == 2 else int(np.prod(shape[:-1]))
                std = fan_in ** -0.5
            value = (rng.standard_normal(shape, dtype=np.float32) * np.float32(std)).astype(np.float32)
        out[path] = jnp.asarray(value)
    return traverse_util.unflatten_dict(out)

"""Octo's block transformer: group attention rules, the pre-LN ViT encoder, and attention capture.

Parameter scopes follow the checkpoint: `BlockTransformer_0/Transformer_0/encoderblock_<i>/
{LayerNorm_0, MultiHeadDotProductAttention_0/{query,key,value,out}, LayerNorm_1, MlpBlock_0/Dense_0,1}`
and `encoder_norm`. Attention is written out here (same parameter shapes as flax's
MultiHeadDotProductAttention: query/key/value kernels `(D, heads, head_dim)`, out kernel
`(heads, head_dim, D)`) so the post-softmax weights can be returned from the same call. Masked logits
take `finfo(float32).min` as in flax, so a fully masked query row becomes uniform over all keys.

Attention rules (Octo's BlockTransformer, all CAUSAL = key timestep <= query timestep; prefix tokens
have timestep -1):
  task_*    -> task_*
  obs_*     -> task_*, obs_*
  readout_X -> task_*, obs_*, readout_X
The final mask is `rule[q, k] AND valid[b, k]` (padding masks keys only).
"""

from __future__ import annotations

from fnmatch import fnmatch
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from harness.octo.config import TransformerConfig

MASKED_LOGIT = float(np.finfo(np.float32).min)


# ----------------------------------------------------------------------------- attention rules (numpy)


def group_rules(group: str) -> tuple[str, ...]:
    """fnmatch patterns of the groups a token of `group` attends to (all causal in time)."""
    if group.startswith("task_"):
        return ("task_*",)
    if group.startswith("readout_"):
        return ("task_*", "obs_*", group)
    return ("task_*", "obs_*")


def _assign_groups(index_in_block: np.ndarray, sizes: Sequence[int], correct: bool) -> np.ndarray:
    """Group index of each token inside a block of consecutive groups.

    Octo 1.5 (`use_correct_attention=True`) uses searchsorted(..., side="right"); the December 2023
    (1.0) models used side="left", which labels the first token of each group with the previous group.
    The 1.0 models were trained with that labelling, so it is reproduced here for them.
    """
    return np.searchsorted(np.cumsum(sizes), index_in_block, side="right" if correct else "left")


def attention_rule_mask(
    prefix_groups: Sequence[tuple[str, int]],
    timestep_groups: Sequence[tuple[str, int]],
    window: int,
    use_correct_attention: bool = True,
) -> np.ndarray:
    """(keys, keys) bool: may query token q attend to key token k by the group rules alone.

    prefix_groups / timestep_groups: [(group name, tokens)] in sequence order.
    """
    n_prefix = sum(n for _, n in prefix_groups)
    per_step = sum(n for _, n in timestep_groups)
    total = n_prefix + per_step * window
    names = [g for g, _ in prefix_groups] + [g for g, _ in timestep_groups]
    i = np.arange(total)
    is_prefix = i < n_prefix
    rel = np.where(is_prefix, 0, i - n_prefix)
    timestep = np.where(is_prefix, -1, rel // max(per_step, 1))
    label = np.empty(total, dtype=np.int64)
    if n_prefix:
        label[is_prefix] = _assign_groups(i[is_prefix], [n for _, n in prefix_groups], use_correct_attention)
    label[~is_prefix] = len(prefix_groups) + _assign_groups(
        rel[~is_prefix] % per_step, [n for _, n in timestep_groups], use_correct_attention
    )
    # (groups, groups): does a token labelled with group a attend to one labelled with group b
    allowed = np.array([[any(fnmatch(b, p) for p in group_rules(a)) for b in names] for a in names], dtype=bool)
    return allowed[label[:, None], label[None, :]] & (timestep[None, :] <= timestep[:, None])


# ----------------------------------------------------------------------------- modules


def masked_softmax(logits: jax.Array, mask: jax.Array | None) -> jax.Array:
    """Softmax over keys with masked logits set to finfo(float32).min (flax's convention: a fully masked
    row becomes uniform). logits (batch, heads, queries, keys); mask broadcastable to it."""
    if mask is not None:
        logits = jnp.where(mask, logits, MASKED_LOGIT)
    return jax.nn.softmax(logits, axis=-1)


class MultiHeadAttention(nn.Module):
    """Dot-product attention returning post-softmax weights: all `(batch, heads, queries, keys)` when
    `capture_rows` is None, else only those query rows `(batch, heads, len(capture_rows), keys)`.

    Captured rows are recomputed from their own queries (a (rows x keys) product per head) instead of
    being sliced out of the full weights, so the main attention stays free to fuse and capture costs
    almost nothing; the values are the same softmax of the same logits.
    """

    num_heads: int
    capture_rows: tuple[int, ...] | None = None

    @nn.compact
    def __call__(self, inputs_q: jax.Array, inputs_kv: jax.Array, mask: jax.Array | None):
        # inputs_q (batch, queries, D); inputs_kv (batch, keys, D); mask broadcastable to (batch, heads, q, k)
        d = inputs_q.shape[-1]
        head_dim = d // self.num_heads
        init = nn.initializers.xavier_uniform()

        def project(name: str, x: jax.Array) -> jax.Array:  # (batch, n, D) -> (batch, n, heads, head_dim)
            return nn.DenseGeneral((self.num_heads, head_dim), axis=-1, kernel_init=init, name=name)(x)

        q = project("query", inputs_q)
        k = project("key", inputs_kv)
        v = project("value", inputs_kv)
        q = q / jnp.sqrt(head_dim).astype(q.dtype)
        weights = masked_softmax(jnp.einsum("bqhd,bkhd->bhqk", q, k), mask)  # (batch, heads, queries, keys)
        # a no-op unless a "perturbations" collection is passed: then d(output)/d(weights) is its gradient
        # (gradient-weighted attention relevance, harness.measures.attribution)
        weights = self.perturb("weights", weights)
        mixed = jnp.einsum("bhqk,bkhd->bqhd", weights, v)
        out = nn.DenseGeneral(d, axis=(-2, -1), kernel_init=init, name="out")(mixed)
        if self.capture_rows is None:
            return out, weights
        rows = np.asarray(self.capture_rows, dtype=np.int32)
        row_mask = None if mask is None else jnp.broadcast_to(mask, weights.shape)[:, :, rows, :]
        row_weights = masked_softmax(jnp.einsum("bqhd,bkhd->bhqk", q[:, rows], k), row_mask)
        return out, row_weights  # (batch, heads, rows, keys)


class MlpBlock(nn.Module):
    """Dense -> gelu (tanh approximation, flax's default) -> Dense."""

    mlp_dim: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        init = nn.initializers.xavier_uniform()
        bias = nn.initializers.normal(stddev=1e-6)
        y = nn.Dense(self.mlp_dim, kernel_init=init, bias_init=bias)(x)
        y = nn.gelu(y)
        return nn.Dense(x.shape[-1], kernel_init=init, bias_init=bias)(y)


class EncoderBlock(nn.Module):
    """Pre-LN block: x + MHA(LN(x)); then + MLP(LN(.))."""

    mlp_dim: int
    num_heads: int
    capture_rows: tuple[int, ...] | None = None

    @nn.compact
    def __call__(self, x: jax.Array, mask: jax.Array):  # (batch, tokens, D), (batch, 1, tokens, tokens)
        y = nn.LayerNorm(name="LayerNorm_0")(x)
        y, weights = MultiHeadAttention(self.num_heads, self.capture_rows, name="MultiHeadDotProductAttention_0")(
            y, y, mask
        )
        x = x + y
        y = nn.LayerNorm(name="LayerNorm_1")(x)
        return x + MlpBlock(self.mlp_dim, name="MlpBlock_0")(y), weights


class Transformer(nn.Module):
    """Encoder stack with attention capture.

    capture_rows: None -> return full weights per layer `(batch, layers, heads, tokens, tokens)`;
    a tuple of query positions -> only those rows `(batch, layers, heads, len(rows), tokens)`.
    """

    config: TransformerConfig
    capture_rows: tuple[int, ...] | None = None
    keep_layer_outputs: bool = False

    @nn.compact
    def __call__(self, x: jax.Array, mask: jax.Array):
        captured, layer_outputs = [], []
        for i in range(self.config.num_layers):
            block = EncoderBlock(self.config.mlp_dim, self.config.num_heads, self.capture_rows, name=f"encoderblock_{i}")
            x, weights = block(x, mask)
            captured.append(weights)
            if self.keep_layer_outputs:
                layer_outputs.append(x)
        encoded = nn.LayerNorm(name="encoder_norm")(x)
        return encoded, jnp.stack(captured, axis=1), layer_outputs


class BlockTransformer(nn.Module):
    """Assembled sequence + key validity -> encoded sequence, captured attention, final mask."""

    config: TransformerConfig
    capture_rows: tuple[int, ...] | None = None
    keep_layer_outputs: bool = False

    @nn.compact
    def __call__(self, tokens: jax.Array, valid: jax.Array, rules: np.ndarray):
        # tokens (batch, N, D); valid (batch, N) bool; rules (N, N) bool numpy
        mask = jnp.logical_and(jnp.asarray(rules)[None, None], valid[:, None, None, :])  # (batch, 1, N, N)
        encoded, weights, layer_outputs = Transformer(
            self.config, self.capture_rows, self.keep_layer_outputs, name="Transformer_0"
        )(tokens, mask)
        return encoded, weights, layer_outputs, mask

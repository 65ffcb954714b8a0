"""T5 text encoder in Flax, parameter-compatible with the `hf_model` subtree of Octo checkpoints.

Octo's LanguageTokenizer runs the encoder half of a Hugging Face T5 model and keeps its weights inside
the Octo checkpoint under `octo_transformer/task_tokenizers_language/hf_model`. This module rebuilds that
encoder (inference only) so the subtree loads as-is:

    shared/embedding                                             (vocab, d_model)
    encoder/block/<i>/layer/0/SelfAttention/{q,k,v,o}/kernel     (d_model, heads*d_kv) / (heads*d_kv, d_model)
    encoder/block/0/layer/0/SelfAttention/relative_attention_bias/embedding   (buckets, heads), block 0 only
    encoder/block/<i>/layer/0/layer_norm/weight                  (d_model,)
    encoder/block/<i>/layer/1/DenseReluDense/{wi,wo}/kernel      (wi_0, wi_1, wo for gated feed-forwards)
    encoder/block/<i>/layer/1/layer_norm/weight                  (d_model,)
    encoder/final_layer_norm/weight                              (d_model,)

T5 specifics: RMS layer norm (no mean subtraction, no bias), no 1/sqrt(d_kv) scaling of q.k, one learned
relative-position bias (bidirectional buckets) computed in block 0 and reused by every block, masked keys
get `finfo(float32).min` added to their logits, dense layers without biases. Everything runs in float32
with the highest matmul precision (the encoder runs once per task, so exactness is worth more than speed).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

_PRECISION = jax.lax.Precision.HIGHEST
_FEED_FORWARDS = ("relu", "gated-gelu", "gated-relu")


class UnknownT5EncoderError(ValueError):
    """The encoder name in an Octo config is neither a built-in T5 nor a folder inside the checkpoint."""


@dataclass(frozen=True)
class T5Config:
    vocab_size: int
    d_model: int
    d_kv: int
    d_ff: int
    num_layers: int
    num_heads: int
    relative_attention_num_buckets: int = 32
    relative_attention_max_distance: int = 128
    layer_norm_epsilon: float = 1e-6
    feed_forward_proj: str = "relu"  # "relu" (t5) or "gated-gelu" / "gated-relu" (t5 v1.1)

    def __post_init__(self):
        if self.feed_forward_proj not in _FEED_FORWARDS:
            raise ValueError(
                f"unsupported T5 feed_forward_proj {self.feed_forward_proj!r}; supported: {', '.join(_FEED_FORWARDS)}"
            )

    @classmethod
    def from_hf_dict(cls, d: dict) -> "T5Config":
        """Reads a Hugging Face T5 `config.json` dict; keys this encoder does not use are ignored."""
        known = {f.name for f in fields(cls)}
        missing = [n for n in ("vocab_size", "d_model", "d_kv", "d_ff", "num_layers", "num_heads") if n not in d]
        if missing:
            raise ValueError(f"T5 config is missing {', '.join(missing)}; pass a Hugging Face T5 config.json")
        return cls(**{k: v for k, v in d.items() if k in known})

    @property
    def inner_dim(self) -> int:
        return self.num_heads * self.d_kv


# google-t5/t5-base (the encoder of every released Octo model).
T5_BASE = T5Config(vocab_size=32128, d_model=768, d_kv=64, d_ff=3072, num_layers=12, num_heads=12)

_BUILTIN = {"t5-base": T5_BASE, "google-t5/t5-base": T5_BASE}


def t5_config_for(encoder_name: str, checkpoint_dir: str | Path | None) -> T5Config:
    """T5 config for the `encoder` name of an Octo LanguageTokenizer.

    Built-in names ("t5-base", "google-t5/t5-base") map to T5_BASE; a relative name such as "t5-tiny" is a
    folder inside the checkpoint directory holding a Hugging Face `config.json`.
    """
    if encoder_name in _BUILTIN:
        return _BUILTIN[encoder_name]
    supported = f"supported: {', '.join(sorted(_BUILTIN))} or a folder with config.json inside the checkpoint"
    name_path = Path(encoder_name)
    if checkpoint_dir is None or name_path.is_absolute() or ".." in name_path.parts:
        raise UnknownT5EncoderError(f"unknown T5 encoder {encoder_name!r}; {supported}")
    config_path = Path(checkpoint_dir) / name_path / "config.json"
    if not config_path.is_file():
        raise UnknownT5EncoderError(f"unknown T5 encoder {encoder_name!r} (no {config_path}); {supported}")
    from harness.bounded import read_json

    return T5Config.from_hf_dict(read_json(config_path))


def relative_position_buckets(length: int, num_buckets: int, max_distance: int) -> np.ndarray:
    """(length, length) int32 bucket of key position k relative to query position q (bidirectional).

    Half the buckets are for keys after the query. Within each half, distances below half of it are exact,
    larger ones share logarithmically wider buckets up to `max_distance`, beyond which they saturate.
    """
    positions = np.arange(length)
    relative = positions[None, :] - positions[:, None]  # (q, k): key minus query
    half = num_buckets // 2
    buckets = np.where(relative > 0, half, 0)
    distance = np.abs(relative)
    max_exact = half // 2
    # Distances below max_exact take the exact branch below, so clamping them keeps the log finite.
    log_ratio = np.log(np.maximum(distance, max_exact) / max_exact) / np.log(max_distance / max_exact)
    large = np.minimum(max_exact + (log_ratio * (half - max_exact)).astype(np.int64), half - 1)
    buckets = buckets + np.where(distance < max_exact, distance, large)
    return buckets.astype(np.int32)


def rms_norm(x: jax.Array, weight: jax.Array, eps: float) -> jax.Array:
    """T5 layer norm over the last axis: weight * x / sqrt(mean(x^2) + eps); no centring, no bias."""
    variance = jnp.mean(jnp.square(x), axis=-1, keepdims=True)
    return weight * (x / jnp.sqrt(variance + eps))


def masked_attention_weights(logits: jax.Array, key_mask: jax.Array) -> jax.Array:
    """Softmax over keys of (batch, heads, q, k) logits; keys where (batch, k) key_mask is False get finfo.min."""
    negative = jnp.where(key_mask, 0.0, jnp.finfo(jnp.float32).min)[:, None, None, :]  # (batch, 1, 1, k)
    return jax.nn.softmax(logits + negative, axis=-1)


class T5LayerNorm(nn.Module):
    epsilon: float

    @nn.compact
    def __call__(self, x):  # (batch, tokens, d_model)
        weight = self.param("weight", nn.initializers.ones, (x.shape[-1],), jnp.float32)
        return rms_norm(x, weight, self.epsilon)


def _dense(features: int, name: str) -> nn.Dense:
    return nn.Dense(features, use_bias=False, dtype=jnp.float32, precision=_PRECISION, name=name)


class T5SelfAttention(nn.Module):
    """Multi-head self-attention; the module owning `relative_attention_bias` also builds the position bias."""

    config: T5Config
    has_relative_bias: bool

    @nn.compact
    def __call__(self, x, key_mask, position_bias):
        # x: (batch, tokens, d_model); key_mask: (batch, tokens) bool; position_bias: (1, heads, q, k) or None
        cfg = self.config
        batch, length, _ = x.shape
        split = lambda y: y.reshape(batch, length, cfg.num_heads, cfg.d_kv)  # noqa: E731
        q = split(_dense(cfg.inner_dim, "q")(x))  # (batch, tokens, heads, d_kv)
        k = split(_dense(cfg.inner_dim, "k")(x))
        v = split(_dense(cfg.inner_dim, "v")(x))
        if self.has_relative_bias:
            buckets = relative_position_buckets(
                length, cfg.relative_attention_num_buckets, cfg.relative_attention_max_distance
            )
            table = nn.Embed(cfg.relative_attention_num_buckets, cfg.num_heads, dtype=jnp.float32,
                             name="relative_attention_bias")
            position_bias = jnp.transpose(table(buckets), (2, 0, 1))[None]  # (1, heads, q, k)
        logits = jnp.einsum("bqhd,bkhd->bhqk", q, k, precision=_PRECISION) + position_bias  # (batch, heads, q, k)
        weights = masked_attention_weights(logits, key_mask)
        out = jnp.einsum("bhqk,bkhd->bqhd", weights, v, precision=_PRECISION).reshape(batch, length, cfg.inner_dim)
        return _dense(cfg.d_model, "o")(out), position_bias


class T5FeedForward(nn.Module):
    """Position-wise feed-forward: ReLU (`wi`, `wo`) or gated GELU/ReLU (`wi_0`, `wi_1`, `wo`)."""

    config: T5Config

    @nn.compact
    def __call__(self, x):  # (batch, tokens, d_model)
        cfg = self.config
        if cfg.feed_forward_proj == "relu":
            hidden = jax.nn.relu(_dense(cfg.d_ff, "wi")(x))
        else:
            act = jax.nn.relu if cfg.feed_forward_proj == "gated-relu" else lambda y: jax.nn.gelu(y, approximate=True)
            hidden = act(_dense(cfg.d_ff, "wi_0")(x)) * _dense(cfg.d_ff, "wi_1")(x)
        return _dense(cfg.d_model, "wo")(hidden)  # (batch, tokens, d_model)


class T5AttentionSublayer(nn.Module):
    config: T5Config
    has_relative_bias: bool

    @nn.compact
    def __call__(self, x, key_mask, position_bias):
        normed = T5LayerNorm(self.config.layer_norm_epsilon, name="layer_norm")(x)
        attended, position_bias = T5SelfAttention(self.config, self.has_relative_bias, name="SelfAttention")(
            normed, key_mask, position_bias
        )
        return x + attended, position_bias


class T5FeedForwardSublayer(nn.Module):
    config: T5Config

    @nn.compact
    def __call__(self, x):
        normed = T5LayerNorm(self.config.layer_norm_epsilon, name="layer_norm")(x)
        return x + T5FeedForward(self.config, name="DenseReluDense")(normed)


class T5Sublayers(nn.Module):
    """The `layer` collection of one block: "0" self-attention, "1" feed-forward (pre-norm residuals)."""

    config: T5Config
    has_relative_bias: bool

    @nn.compact
    def __call__(self, x, key_mask, position_bias):
        attention = T5AttentionSublayer(self.config, self.has_relative_bias, name="0")
        x, position_bias = attention(x, key_mask, position_bias)
        return T5FeedForwardSublayer(self.config, name="1")(x), position_bias


class T5Block(nn.Module):
    config: T5Config
    has_relative_bias: bool

    @nn.compact
    def __call__(self, x, key_mask, position_bias):
        return T5Sublayers(self.config, self.has_relative_bias, name="layer")(x, key_mask, position_bias)


class T5Blocks(nn.Module):
    """The `block` collection: blocks "0".."num_layers-1"; block 0 computes the shared position bias."""

    config: T5Config

    @nn.compact
    def __call__(self, x, key_mask):
        position_bias = None
        for i in range(self.config.num_layers):
            x, position_bias = T5Block(self.config, i == 0, name=str(i))(x, key_mask, position_bias)
        return x


class T5Stack(nn.Module):
    config: T5Config

    @nn.compact
    def __call__(self, x, key_mask):
        x = T5Blocks(self.config, name="block")(x, key_mask)
        return T5LayerNorm(self.config.layer_norm_epsilon, name="final_layer_norm")(x)


class T5Encoder(nn.Module):
    """T5 encoder: token ids -> last_hidden_state, parameters named as Hugging Face's Flax T5 encoder."""

    config: T5Config

    @nn.compact
    def __call__(self, input_ids, attention_mask):
        # input_ids, attention_mask: (batch, tokens) int -> (batch, tokens, d_model) float32
        cfg = self.config
        embed = nn.Embed(cfg.vocab_size, cfg.d_model, dtype=jnp.float32, name="shared")
        x = embed(jnp.asarray(input_ids, jnp.int32))  # (batch, tokens, d_model)
        key_mask = jnp.asarray(attention_mask) > 0  # (batch, tokens)
        return T5Stack(cfg, name="encoder")(x, key_mask)

"""Action heads: the diffusion score network, the continuous (L1/MSE) head, and MAP pooling.

Parameter scopes follow the checkpoint under `heads_<name>/`:
  diffusion: `diffusion_model/{time_preprocess/kernel, cond_encoder/Dense_0,1, reverse_network/{Dense_0,
             MLPResNetBlock_<i>/{LayerNorm_0, Dense_0, Dense_1}, Dense_1}}`
  continuous: `mean_proj`
  either, with use_map: `map_head/{probe, MultiHeadDotProductAttention_0, LayerNorm_0, MlpBlock_0}`

Score network (Octo's ScoreActor): Fourier features of the raw integer step t,
`cond = Dense(swish(Dense(fourier)))`, then an MLP-ResNet on `concat[cond, readout_embedding, x_t]`.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from harness.octo.config import ContinuousHeadConfig, DiffusionHeadConfig, MapHeadConfig
from harness.octo.transformer import MlpBlock, MultiHeadAttention

_xavier = nn.initializers.xavier_uniform


class FourierFeatures(nn.Module):
    """Learnable Fourier features: `(..., 1)` time -> `(..., output_size)` = [cos(2 pi t W^T), sin(...)]."""

    output_size: int

    @nn.compact
    def __call__(self, t: jax.Array) -> jax.Array:
        w = self.param("kernel", nn.initializers.normal(0.2), (self.output_size // 2, t.shape[-1]), jnp.float32)
        f = 2 * jnp.pi * t @ w.T
        return jnp.concatenate([jnp.cos(f), jnp.sin(f)], axis=-1)


class TimeEncoder(nn.Module):
    """MLP (2*time_dim, time_dim) with swish between the layers."""

    time_dim: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        x = nn.Dense(2 * self.time_dim, kernel_init=_xavier())(x)
        x = nn.swish(x)
        return nn.Dense(self.time_dim, kernel_init=_xavier())(x)


class MLPResNetBlock(nn.Module):
    features: int
    use_layer_norm: bool

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        y = nn.LayerNorm()(x) if self.use_layer_norm else x
        y = nn.Dense(self.features * 4)(y)
        y = nn.swish(y)
        return x + nn.Dense(self.features)(y)


class MLPResNet(nn.Module):
    num_blocks: int
    out_dim: int
    hidden_dim: int
    use_layer_norm: bool

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        x = nn.Dense(self.hidden_dim, kernel_init=_xavier())(x)
        for _ in range(self.num_blocks):
            x = MLPResNetBlock(self.hidden_dim, self.use_layer_norm)(x)
        x = nn.swish(x)
        return nn.Dense(self.out_dim, kernel_init=_xavier())(x)


class ScoreNetwork(nn.Module):
    """eps(readout embedding `(..., D)`, noisy flat actions `(..., horizon*dim)`, step `(..., 1)` int)."""

    config: DiffusionHeadConfig

    @nn.compact
    def __call__(self, embedding: jax.Array, noisy_actions: jax.Array, time: jax.Array) -> jax.Array:
        cfg = self.config
        fourier = FourierFeatures(cfg.time_dim, name="time_preprocess")(time)
        cond = TimeEncoder(cfg.time_dim, name="cond_encoder")(fourier)
        embedding = jnp.broadcast_to(embedding, cond.shape[:-1] + embedding.shape[-1:])
        x = jnp.concatenate([cond, embedding, noisy_actions], axis=-1)
        return MLPResNet(
            cfg.num_blocks, cfg.action_horizon * cfg.action_dim, cfg.hidden_dim, cfg.use_layer_norm,
            name="reverse_network",
        )(x)


class MAPHead(nn.Module):
    """Multi-head attention pooling: tokens `(..., n, D)` + mask `(..., n)` -> `(..., readouts, D)`."""

    config: MapHeadConfig

    @nn.compact
    def __call__(self, tokens: jax.Array, mask: jax.Array | None) -> jax.Array:
        cfg = self.config
        *batch, n, d = tokens.shape
        x = tokens.reshape(-1, n, d)
        probe = self.param("probe", _xavier(), (1, cfg.num_readouts, d), x.dtype)
        probe = jnp.tile(probe, [x.shape[0], 1, 1])
        if mask is not None:
            mask = jnp.broadcast_to(mask.reshape(-1, n)[:, None, None, :], (x.shape[0], 1, cfg.num_readouts, n))
        out, _ = MultiHeadAttention(cfg.num_heads, name="MultiHeadDotProductAttention_0")(probe, x, mask)
        y = nn.LayerNorm(name="LayerNorm_0")(out)
        out = out + MlpBlock(cfg.mlp_dim or 4 * d, name="MlpBlock_0")(y)
        return out.reshape(*batch, cfg.num_readouts, d)


def pool_readouts(head_params: dict, config: DiffusionHeadConfig | ContinuousHeadConfig,
                  tokens: jax.Array, mask: jax.Array) -> jax.Array:
    """Readout tokens `(batch, window, n, D)` -> embedding `(batch, window, D)` (mean, or MAP if use_map)."""
    if config.use_map:
        pooled = MAPHead(config.map_head).apply({"params": head_params["map_head"]}, tokens, mask)
        return pooled[:, :, 0]
    return tokens.mean(axis=-2)


class ContinuousHead(nn.Module):
    """L1/MSE head: embedding `(batch, window, D)` -> actions `(batch, window, horizon, dim)` in +-max_action."""

    config: ContinuousHeadConfig

    @nn.compact
    def __call__(self, embedding: jax.Array) -> jax.Array:
        cfg = self.config
        mean = nn.Dense(cfg.action_horizon * cfg.action_dim, name="mean_proj")(embedding)
        mean = mean.reshape(*mean.shape[:-1], cfg.action_horizon, cfg.action_dim)
        return jnp.tanh(mean / cfg.max_action) * cfg.max_action


def init_head_params(rng: jax.Array, config: DiffusionHeadConfig | ContinuousHeadConfig, embed_dim: int,
                     readout_tokens: int) -> dict:
    """Fresh parameters of one head, laid out as `heads_<name>` in Octo's checkpoints."""
    k_map, k_net = jax.random.split(rng)
    params = {}
    if config.use_map:
        tokens = jnp.zeros((1, 1, readout_tokens, embed_dim), jnp.float32)
        params["map_head"] = MAPHead(config.map_head).init(k_map, tokens, None)["params"]
    embedding = jnp.zeros((1, 1, embed_dim), jnp.float32)
    if isinstance(config, DiffusionHeadConfig):
        flat = jnp.zeros((1, 1, config.action_horizon * config.action_dim), jnp.float32)
        time = jnp.zeros((1, 1, 1), jnp.float32)
        params["diffusion_model"] = ScoreNetwork(config).init(k_net, embedding, flat, time)["params"]
    else:
        params.update(ContinuousHead(config).init(k_net, embedding)["params"])
    return params

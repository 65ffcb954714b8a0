"""Observation tokenizers: images -> patch tokens (SmallStem / PatchEncoder), low-dim vectors -> tokens.

Parameter scopes follow Octo's checkpoints: an `ImageTokenizer` scope (`observation_tokenizers_<name>`)
holds one encoder scope named `<Octo class>_0` (e.g. `SmallStem16_0`) with `StdConv_i`, `GroupNorm_i`
and the patchifying conv `embedding`.

Octo stacks the observation image and the goal image channel-wise before the stem
(`(batch, window, H, W, 3+3)`), normalises pixels to [-1, 1] (so an all-zero goal becomes -1), and
masks a whole image group when `pad_mask_dict[key]` is False.
"""

from __future__ import annotations

import re
from typing import Mapping, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from harness.octo.config import ImageTokenizerConfig, LowdimTokenizerConfig, StemConfig

_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)
_BIN_EPS = 1e-6


def regex_filter(patterns: Sequence[str], keys: Sequence[str]) -> list[str]:
    """Keys (in the given order) matched from their start by any pattern, as Octo's regex_filter."""
    return [k for k in keys if any(re.match(p, k) for p in patterns)]


def normalize_images(images: jax.Array, norm_type: str = "default") -> jax.Array:
    """uint8 `(..., H, W, 3k)` -> float32 in Octo's input range ("default": [-1, 1])."""
    x = images.astype(jnp.float32)
    if norm_type == "default":
        return x / 127.5 - 1.0
    x = x / 255
    reps = x.shape[-1] // 3
    mean = jnp.tile(jnp.asarray(_IMAGENET_MEAN, jnp.float32), reps)
    std = jnp.tile(jnp.asarray(_IMAGENET_STD, jnp.float32), reps)
    return (x - mean) / std


def standardize_weights(kernel: jax.Array, eps: float = 1e-5) -> jax.Array:
    """Weight standardisation of a conv kernel `(kh, kw, c_in, c_out)` over all but the output axis."""
    axes = (0, 1, 2)
    centred = kernel - jnp.mean(kernel, axis=axes)
    return centred / (jnp.std(centred, axis=axes) + eps)


class StdConv(nn.Module):
    """Conv with weight standardisation (eps 1e-5), symmetric integer padding."""

    features: int
    kernel_size: int
    stride: int
    padding: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:  # (n, h, w, c_in) -> (n, h', w', features)
        k = self.kernel_size
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (k, k, x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))
        y = jax.lax.conv_general_dilated(
            x,
            standardize_weights(kernel),
            window_strides=(self.stride, self.stride),
            padding=((self.padding, self.padding), (self.padding, self.padding)),
            dimension_numbers=("NHWC", "HWIO", "NHWC"),
        )
        return y + bias


class SmallStem(nn.Module):
    """Octo's SmallStem*/PatchEncoder: `(n, H, W, c)` uint8 -> `(n, rows, cols, num_features)`."""

    config: StemConfig

    @nn.compact
    def __call__(self, images: jax.Array) -> jax.Array:
        cfg = self.config
        x = normalize_images(images, cfg.img_norm_type)
        if cfg.is_patch_encoder:
            p = cfg.patch_size
            return nn.Conv(cfg.num_features, (p, p), strides=(p, p), padding="VALID", name="embedding")(x)
        for k, s, f, p in zip(cfg.kernel_sizes, cfg.strides, cfg.features, cfg.padding):
            x = StdConv(features=f, kernel_size=k, stride=s, padding=p)(x)
            # two-pass variance: equal to the original's E[x^2]-E[x]^2 in exact arithmetic, but it does not
            # amplify float32 rounding (measured against a float64 forward: ~half the original's error)
            x = nn.GroupNorm(num_groups=32, epsilon=1e-6, use_fast_variance=False)(x)
            x = nn.relu(x)
        e = max(cfg.patch_size // 16, 1)
        return nn.Conv(cfg.num_features, (e, e), strides=(e, e), padding="VALID", name="embedding")(x)


def _pad_mask(pad_mask_dict: Mapping[str, jax.Array] | None, keys: Sequence[str], shape: tuple[int, ...]) -> jax.Array:
    """Octo's proper pad mask: any of `keys` present, broadcast over tokens; all ones when unknown."""
    if pad_mask_dict is None or not all(k in pad_mask_dict for k in keys):
        return jnp.ones(shape, dtype=bool)
    present = jnp.any(jnp.stack([jnp.asarray(pad_mask_dict[k], bool) for k in keys], axis=-1), axis=-1)
    return jnp.broadcast_to(present[..., None], shape)


def image_stack_keys(cfg: ImageTokenizerConfig, observation_keys: Sequence[str]) -> list[str]:
    """Observation keys this tokenizer stacks (sorted, as Octo); empty -> the tokenizer is skipped."""
    return regex_filter(cfg.obs_stack_keys, sorted(observation_keys))


class ImageTokenizer(nn.Module):
    """Stacks observation (+ goal) images and runs the stem: tokens `(batch, window, rows*cols, features)`."""

    config: ImageTokenizerConfig

    @nn.compact
    def __call__(self, observations: Mapping[str, jax.Array], task: Mapping[str, jax.Array] | None):
        cfg = self.config
        obs_keys = image_stack_keys(cfg, list(observations))
        x = jnp.concatenate([observations[k] for k in obs_keys], axis=-1)  # (b, t, H, W, c)
        b, t = x.shape[:2]
        if cfg.task_stack_keys:
            goals = dict(task or {})
            for k in regex_filter(cfg.task_stack_keys, list(observations)):
                if k not in goals:  # missing goal images are zeros, as in Octo
                    goals[k] = jnp.zeros_like(observations[k][:, 0])
            goal_keys = regex_filter(cfg.task_stack_keys, sorted(goals))
            goal = jnp.concatenate([goals[k] for k in goal_keys], axis=-1)  # (b, H, W, c)
            x = jnp.concatenate([x, jnp.broadcast_to(goal[:, None], (b, t, *goal.shape[1:]))], axis=-1)
        stem = SmallStem(cfg.encoder, name=f"{cfg.encoder.module_name}_0")
        tokens = stem(x.reshape(b * t, *x.shape[2:]))  # (b*t, rows, cols, f)
        tokens = tokens.reshape(b, t, -1, tokens.shape[-1])
        if cfg.proper_pad_mask:
            mask = _pad_mask(observations.get("pad_mask_dict"), obs_keys, tokens.shape[:-1])
        else:
            mask = jnp.ones(tokens.shape[:-1], dtype=bool)
        return tokens, mask


def lowdim_stack_keys(cfg: LowdimTokenizerConfig, observation_keys: Sequence[str]) -> list[str]:
    """Observation keys concatenated by a LowdimObsTokenizer, in Octo's order (per pattern, sorted)."""
    keys = sorted(observation_keys)
    return [k for p in cfg.obs_keys for k in keys if re.match(p, k)]


def lowdim_tokens(cfg: LowdimTokenizerConfig, observations: Mapping[str, jax.Array]):
    """`(batch, window, dims)` vectors -> tokens `(batch, window, dims, 1 or n_bins)` and an all-ones mask."""
    x = jnp.concatenate([jnp.asarray(observations[k], jnp.float32) for k in lowdim_stack_keys(cfg, list(observations))], -1)
    if cfg.discretize:
        if cfg.bin_type == "uniform":
            thresholds = jnp.linspace(cfg.low, cfg.high, cfg.n_bins + 1)
            x = jnp.clip(x, cfg.low + _BIN_EPS, cfg.high - _BIN_EPS)
        else:
            thresholds = jax.scipy.stats.norm.ppf(jnp.linspace(_BIN_EPS, 1 - _BIN_EPS, cfg.n_bins + 1))
        xe = x[..., None]
        one_hot = (xe < thresholds[1:]) & (xe >= thresholds[:-1])
        tokens = jax.nn.one_hot(jnp.argmax(one_hot.astype(jnp.uint8), axis=-1), cfg.n_bins)
    else:
        tokens = x[..., None]
    return tokens, jnp.ones(tokens.shape[:-1], dtype=bool)


def num_image_tokens(cfg: ImageTokenizerConfig, height: int, width: int) -> tuple[int, int]:
    """(rows, cols) of the token grid for a (height, width) input image."""
    return cfg.encoder.grid(height, width)


__all__ = [
    "ImageTokenizer", "SmallStem", "StdConv", "image_stack_keys", "lowdim_stack_keys", "lowdim_tokens",
    "normalize_images", "num_image_tokens", "regex_filter", "standardize_weights",
]

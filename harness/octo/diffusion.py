"""DDPM sampling of Octo's diffusion action head, as pure functions.

Schedule: cosine (s=0.008), betas clipped to [0, 0.999], `diffusion_steps` steps (20).
Sampler (Octo's DiffusionActionHead.predict_action), x of shape (batch, window, horizon*dim):

    rng, key = split(rng); x = normal(key, shape)
    for t in steps-1 .. 0:
        eps = score(x, t)
        x = (x - (1 - alpha_t) / sqrt(1 - alpha_hat_t) * eps) * (1 / sqrt(alpha_t))
        rng, key = split(rng); z = normal(key, shape)          # drawn at t = 0 too
        x = clip(x + (t > 0) * sqrt(beta_t) * z, -max_action, max_action)
        x = where(action_mask, x, sqrt(1 - alpha_hat_t) * z)

All window positions are denoised; callers keep the last one.

Samplers: "latest" is the loop above, as the latest original code (octo-models/octo 241fb35, the 1.5
release) runs it for every checkpoint, 1.0-format ones included. "v0.1.0" is the December 2023 code
(tag v0.1.0): it sampled inside `vmap` over `split(rng, n_samples)` with one sample, i.e. the key is
split once more before the loop (so every draw differs), and it had no action mask.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

SAMPLERS = ("latest", "v0.1.0")

import jax
import jax.numpy as jnp


class Schedule(NamedTuple):
    betas: jax.Array  # (steps,) float32
    alphas: jax.Array  # (steps,)
    alpha_hats: jax.Array  # (steps,) cumulative products of alphas


def cosine_beta_schedule(steps: int, s: float = 0.008) -> jax.Array:
    """(steps,) float32 betas of the cosine schedule, clipped to [0, 0.999]."""
    t = jnp.linspace(0, steps, steps + 1) / steps
    alphas_cumprod = jnp.cos((t + s) / (1 + s) * jnp.pi * 0.5) ** 2
    alphas_cumprod = alphas_cumprod / alphas_cumprod[0]
    betas = 1 - (alphas_cumprod[1:] / alphas_cumprod[:-1])
    return jnp.clip(betas, 0, 0.999)


def make_schedule(steps: int) -> Schedule:
    betas = cosine_beta_schedule(steps)
    alphas = 1 - betas
    return Schedule(betas, alphas, jnp.cumprod(alphas))


def denoise_step(x: jax.Array, eps: jax.Array, t: jax.Array, z: jax.Array, schedule: Schedule,
                 max_action: float, action_mask: jax.Array | None = None) -> jax.Array:
    """One reverse step x_t -> x_{t-1} given the predicted eps and the step's noise z (shapes of x)."""
    alpha_1 = 1 / jnp.sqrt(schedule.alphas[t])
    alpha_2 = (1 - schedule.alphas[t]) / jnp.sqrt(1 - schedule.alpha_hats[t])
    x = alpha_1 * (x - alpha_2 * eps)
    x = x + (t > 0) * (jnp.sqrt(schedule.betas[t]) * z)
    x = jnp.clip(x, -max_action, max_action)
    if action_mask is not None:
        x = jnp.where(action_mask, x, jnp.sqrt(1 - schedule.alpha_hats[t]) * z)
    return x


def sample(score: Callable[[jax.Array, jax.Array], jax.Array], rng: jax.Array, shape: tuple[int, ...],
           schedule: Schedule, max_action: float, action_mask: jax.Array | None = None,
           sampler: str = "latest") -> jax.Array:
    """Run the reverse process from pure noise; returns x_0 of `shape` (batch, window, horizon*dim).

    score(x, t) -> eps, with t a scalar int32 step. sampler "latest" or "v0.1.0" (see the module
    docstring; "v0.1.0" ignores action_mask, which that code did not have).
    """
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; use one of {', '.join(SAMPLERS)}")
    if sampler == "v0.1.0":
        rng = jax.random.split(rng, 1)[0]
        action_mask = None
    rng, key = jax.random.split(rng)
    x = jax.random.normal(key, shape)
    steps = schedule.betas.shape[0]

    def body(carry, t):
        x, rng = carry
        eps = score(x, t)
        rng, key = jax.random.split(rng)
        z = jax.random.normal(key, x.shape)
        return (denoise_step(x, eps, t, z, schedule, max_action, action_mask), rng), None

    (x, _), _ = jax.lax.scan(body, (x, rng), jnp.arange(steps - 1, -1, -1))
    return x

"""One training step of the reference policy (reference_policies.train): random-shift augmentation, the readout
embedding the action head reads, Octo's two head losses over the valid entries of each action chunk, the update.

The forward pass is the runtime's own Flax modules (`OctoTransformer`, `pool_readouts`, `ContinuousHead`,
`ScoreNetwork`), so the parameter names are Octo's; the losses are Octo's L1ActionHead and DiffusionActionHead
losses (see reference_policies.train's docstring for why L1 is the default).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import optax

from harness.octo.config import DiffusionHeadConfig, OctoConfig
from harness.octo.diffusion import make_schedule
from harness.octo.heads import ContinuousHead, ScoreNetwork, pool_readouts
from harness.octo.network import OctoTransformer


def shift_images(images: jax.Array, offsets: jax.Array, pad: int) -> jax.Array:
    """Random-shift augmentation: (b, H, W, 3) uint8, (b, 2) int offsets in [0, 2 pad] -> (b, H, W, 3)."""
    h, w = images.shape[1:3]
    padded = jnp.pad(images, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")
    crop = lambda img, o: jax.lax.dynamic_slice(img, (o[0], o[1], 0), (h, w, 3))  # noqa: E731
    return jax.vmap(crop)(padded, offsets)


def readout_embedding(params: dict, config: OctoConfig, batch: dict, encodings: jax.Array) -> jax.Array:
    """The action head's input (b, 1, D): the transformer's readout tokens, pooled as the head does.

    batch: image_<key> (b, 1, S, S, 3) uint8, proprio (b, 1, 8), instruction (b,) int32 index into
    encodings (k, tokens, d_t5); params without the frozen T5 encoder.
    """
    head = config.action_head
    b = batch["proprio"].shape[0]
    obs = {k: v for k, v in batch.items() if k.startswith("image_") or k == "proprio"}
    ones = jnp.ones((b, 1), bool)
    obs["pad_mask_dict"] = {k: ones for k in obs}
    task = {"pad_mask_dict": {"language_instruction": jnp.ones((b,), bool)}}
    encoding = encodings[batch["instruction"]]
    out = OctoTransformer(config, capture_rows=()).apply({"params": params["octo_transformer"]}, obs, task, encoding, ones)
    tokens, mask = out["groups"][head.readout_key]
    return pool_readouts(params["heads_action"], head, tokens, mask)  # (b, 1, D)


def _chunk_mask(batch: dict, head) -> jax.Array:
    """(b, horizon, dim) float32: 1 for chunk entries inside the episode."""
    b = batch["action_mask"].shape[0]
    return jnp.broadcast_to(batch["action_mask"][:, :, None], (b, head.action_horizon, head.action_dim)).astype(jnp.float32)


def l1_loss(params: dict, config: OctoConfig, batch: dict, encodings: jax.Array, rng: jax.Array,
            alpha_hats: jax.Array | None = None) -> jax.Array:
    """Octo's L1ActionHead loss: mean |predicted - normalised action| over valid chunk entries (rng unused)."""
    head = config.action_head
    embedding = readout_embedding(params, config, batch, encodings)
    predicted = ContinuousHead(head).apply({"params": {"mean_proj": params["heads_action"]["mean_proj"]}}, embedding)[:, 0]
    target = jnp.clip(batch["actions"], -head.max_action, head.max_action)  # (b, horizon, 7)
    mask = _chunk_mask(batch, head)
    return jnp.sum(jnp.abs(predicted - target) * mask) / jnp.maximum(jnp.sum(mask), 1)


def diffusion_loss(params: dict, config: OctoConfig, batch: dict, encodings: jax.Array, rng: jax.Array,
                   alpha_hats: jax.Array) -> jax.Array:
    """Octo's DiffusionActionHead loss (eps MSE over valid chunk entries); batch as `readout_embedding` plus
    actions (b, horizon, 7) normalised and action_mask (b, horizon) bool."""
    head = config.action_head
    b = batch["actions"].shape[0]
    embedding = readout_embedding(params, config, batch, encodings)
    actions = jnp.clip(batch["actions"], -head.max_action, head.max_action).reshape(b, 1, -1)  # (b, 1, horizon*7)
    t_key, n_key = jax.random.split(rng)
    t = jax.random.randint(t_key, (b, 1, 1), 0, head.diffusion_steps)
    noise = jax.random.normal(n_key, actions.shape)
    alpha_hat = alpha_hats[t]
    noisy = jnp.sqrt(alpha_hat) * actions + jnp.sqrt(1 - alpha_hat) * noise
    eps = ScoreNetwork(head).apply({"params": params["heads_action"]["diffusion_model"]}, embedding, noisy,
                                   t.astype(jnp.float32))
    mask = _chunk_mask(batch, head).reshape(b, 1, -1)
    return jnp.sum(jnp.square(eps - noise) * mask) / jnp.maximum(jnp.sum(mask), 1)


@functools.lru_cache(maxsize=8)
def make_optimizer(grad_clip: float, weight_decay: float):
    """AdamW (optax's defaults) after global-norm clipping, without its learning rate: the training step scales
    the update by the rate it is given, so that the schedule is an input of the compiled step, not a constant of it
    (trainings that differ only in schedule, steps or T5 encodings share one XLA program and its persistent cache).
    The same update as `optax.chain(clip_by_global_norm, adamw(schedule))` with the schedule read at the count.
    One object per (grad_clip, weight_decay), so that make_train_step finds its compiled step again."""
    return optax.chain(optax.clip_by_global_norm(grad_clip), optax.scale_by_adam(),
                       optax.add_decayed_weights(weight_decay))


def make_train_step(config: OctoConfig, optimizer, schedule, encodings: jax.Array, image_keys: tuple[str, ...],
                    shift_pixels: int):
    """The step (trainable, optimiser state, batch, rng, count) -> (trainable, optimiser state, loss): each camera's
    images randomly shifted, then the head's loss (L1 or diffusion), its gradient, `optimizer`'s (`make_optimizer`)
    update and a descent of `schedule(count)` along it, `count` being the updates made before this one (from 0).
    The schedule's value and the T5 `encodings` are arguments of the jitted function, and the jitted function is
    one per (config, optimizer, image_keys, shift_pixels) in a process: a later training of the same network (a
    DAgger round's fine-tuning after its stage 1) reuses the traced and compiled step instead of tracing, lowering
    and loading it again (about 10 s of CPU a training)."""
    update = _jitted_update(config, optimizer, tuple(image_keys), shift_pixels)

    def train_step(trainable, opt_state, batch, rng, count: int):
        return update(trainable, opt_state, batch, rng, jnp.float32(schedule(count)), encodings)

    return train_step


@functools.lru_cache(maxsize=8)
def _jitted_update(config: OctoConfig, optimizer, image_keys: tuple[str, ...], shift_pixels: int):
    """make_train_step's jitted update, made once per (hashable, frozen) configuration and optimizer object."""
    diffusion = isinstance(config.action_head, DiffusionHeadConfig)
    alpha_hats = make_schedule(config.action_head.diffusion_steps).alpha_hats if diffusion else None
    loss_fn = diffusion_loss if diffusion else l1_loss

    @jax.jit
    def update(trainable, opt_state, batch, rng, learning_rate, encodings):
        aug_key, loss_key = jax.random.split(rng)
        batch = dict(batch)
        for i, k in enumerate(image_keys):
            offsets = jax.random.randint(jax.random.fold_in(aug_key, i), (batch[k].shape[0], 2), 0, 2 * shift_pixels + 1)
            batch[k] = shift_images(batch[k][:, 0], offsets, shift_pixels)[:, None]
        loss, grads = jax.value_and_grad(loss_fn)(trainable, config, batch, encodings, loss_key, alpha_hats)
        updates, opt_state = optimizer.update(grads, opt_state, trainable)
        updates = jax.tree.map(lambda u: -learning_rate * u, updates)
        return optax.apply_updates(trainable, updates), opt_state, loss

    return update

"""Attribution methods: per-patch scores of what the policy's action depends on, one signature for all.

The policy's own function at one control step is a `StepFunction`: images (the frames the model reads,
float pixels 0..255) -> the normalised action chunk (horizon, action_dim), with the same rng, plus the full
attention of every layer. `analyse(step)` runs it once forward and once backward (one `jax.vjp`) and keeps
what every method needs (`StepAnalysis`); the methods are then pure numpy functions
`method(analysis) -> {observation key: (rows, cols)}` on the current frame's patch grid of each camera
(Captum's shape: any method is interchangeable with any other; a new one is one function and one row of the
table `METHODS`, which also holds the one default list, DEFAULT_METHODS):

  attention:<layer>   raw readout attention of a layer, mean over heads and readout tokens
  rollout             attention rollout (Abnar & Zuidema 2020; harness.measures.attention)
  grad-attention      gradient-weighted attention relevance (Chefer, Gur & Wolf 2021, "Transformer
                      Interpretability Beyond Attention Visualization", their rule for self-attention):
                      R = I; per layer R <- R + mean_heads[(dS/dA ⊙ A)^+] @ R; the readout rows of R
  saliency            |dS/d pixels| summed over the channels and pixels of each patch (through the image
                      tokenizer; Simonyan et al. 2014)
  occlusion           the chunk's change when that one patch alone is deleted (mean fill; Zeiler & Fergus 2014):
                      one forward pass per patch; what a deletion curve's first point measures, so the reference
                      a faithful map is compared with (costly on large grids)
  random              uniform random scores, seeded: the control every method is measured against

The scalar S differentiated is the action chunk's projection on its own direction, S = <a, stop(a)/|a|>
(a: the normalised chunk, flattened), so dS/dx = J^T a/|a|: the input change that moves the predicted
chunk along itself, at the cost of one backward pass for any chunk size (the full Jacobian would cost one
pass per action number). The diffusion head samples with the step's fixed rng, so S is a deterministic,
differentiable function of the pixels; the L1 head is differentiated directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from harness.measures.attention import camera_keys, patch_index, rollout_readout_rows
from harness.octo.tokens import TokenMap

@dataclass(frozen=True, eq=False)
class StepFunction:
    """The policy's function at one step: `fn(images, perturbation) -> (actions, attention)`.

    images: {observation key: (window, H, W, 3) float32, 0..255} at the model's sizes (`images` holds the
    step's own inputs); perturbation (layers, heads, keys, keys) float32 added to every layer's post-softmax
    attention (zeros: the policy unchanged; its gradient is dS/dA); actions (horizon, action_dim) normalised;
    attention (layers, heads, keys, keys). `batch(images)` evaluates many image sets at once:
    {key: (n, window, H, W, 3)} -> (n, horizon, action_dim).
    """

    fn: Callable
    batch: Callable
    images: dict[str, np.ndarray]
    tokens: TokenMap
    shape: tuple[int, int, int]  # (layers, heads, keys)


@dataclass(frozen=True, eq=False)
class StepAnalysis:
    """One forward and one backward pass of a StepFunction (what every attribution method reads)."""

    actions: np.ndarray  # (horizon, action_dim) normalised
    attention: np.ndarray  # (layers, heads, keys, keys)
    grad_attention: np.ndarray  # (layers, heads, keys, keys) dS/dA
    grad_images: dict[str, np.ndarray]  # {key: (window, H, W, 3)} dS/dpixels
    tokens: TokenMap
    occlusion: dict[str, np.ndarray] | None = None  # {key: (rows, cols)} single-patch deletion change, when computed


def direction_score(actions: jax.Array) -> jax.Array:
    """S = <a, stop(a)/|a|> over the flattened chunk (0 for a zero chunk)."""
    a = actions.reshape(-1)
    u = jax.lax.stop_gradient(a)
    norm = jnp.linalg.norm(u)
    return jnp.where(norm > 0, jnp.dot(a, u) / jnp.where(norm > 0, norm, 1.0), 0.0)


def analyse(step: StepFunction, gradients: bool = True, occlusion: bool = False) -> StepAnalysis:
    """Forward + one vjp of S with respect to the images and the attention perturbation.

    gradients=False: the forward pass only (enough for attention and rollout; the gradients are zeros).
    occlusion=True: also one forward pass per patch of every camera (the `occlusion` method).
    """
    zeros = jnp.zeros(step.shape[:2] + (step.shape[2], step.shape[2]), jnp.float32)

    def score(images, perturbation):
        actions, attention = step.fn(images, perturbation)
        return direction_score(actions), (actions, attention)

    images = {k: jnp.asarray(v, jnp.float32) for k, v in step.images.items()}
    if gradients:
        (_, (actions, attention)), (g_images, g_attention) = _value_and_grad(score)(images, zeros)
    else:
        actions, attention = step.fn(images, zeros)
        g_images = {k: np.zeros_like(v) for k, v in step.images.items()}
        g_attention = np.zeros(zeros.shape, np.float32)
    actions = np.asarray(actions, np.float32)
    return StepAnalysis(
        actions=actions,
        attention=np.asarray(attention, np.float32),
        grad_attention=np.asarray(g_attention, np.float32),
        grad_images={k: np.asarray(v, np.float32) for k, v in g_images.items()},
        tokens=step.tokens,
        occlusion=occlusion_maps(step, actions) if occlusion else None,
    )


def occlusion_maps(step: StepFunction, reference: np.ndarray, fill: str = "mean") -> dict[str, np.ndarray]:
    """{obs key: (rows, cols)} RMS change of the chunk when that patch alone of the current frame is deleted."""
    from harness.measures.faithfulness import action_change, delete_patches

    out = {}
    for _, key, rows, cols in step.tokens.image_groups:
        frame = np.asarray(step.images[key][-1], np.float32)
        single = np.eye(rows * cols, dtype=bool).reshape(rows * cols, rows, cols)
        inputs = {k: np.repeat(np.asarray(v, np.float32)[None], rows * cols, axis=0) for k, v in step.images.items()}
        inputs[key][:, -1] = delete_patches(frame, single, fill)
        out[key] = action_change(step.batch(inputs), reference).reshape(rows, cols)
    return out


def _value_and_grad(score):
    return jax.value_and_grad(score, argnums=(0, 1), has_aux=True)


# ------------------------------------------------------------------------------------------- methods (pure)


def _readout_maps(rows: np.ndarray, tokens: TokenMap) -> dict[str, np.ndarray]:
    """rows (keys,) over the sequence -> {obs key: (rows, cols)} of the current timestep's patches."""
    out = {}
    for group, key, r, c in tokens.image_groups:
        out[key] = np.asarray(rows)[camera_keys(tokens, key, -1)].reshape(r, c).astype(np.float64)
    return out


def attention_map(analysis: StepAnalysis, layer: int) -> dict[str, np.ndarray]:
    """Raw readout attention of `layer` (negative counts from the end), mean over heads and readouts."""
    layers = analysis.attention.shape[0]
    if not -layers <= layer < layers:
        raise ValueError(f"layer {layer} is outside the model's {layers} layers")
    rows = analysis.attention[layer][:, analysis.tokens.readout_index, :].mean(axis=(0, 1))  # (keys,)
    return _readout_maps(rows, analysis.tokens)


def rollout_map(analysis: StepAnalysis) -> dict[str, np.ndarray]:
    """Attention rollout (residual 0.5, head mean) readout rows, mean over readouts."""
    rows = rollout_readout_rows(analysis.attention, analysis.tokens).mean(axis=0)
    return _readout_maps(rows, analysis.tokens)


def gradient_relevance(attention: np.ndarray, grad: np.ndarray) -> np.ndarray:
    """Chefer et al. (2021) relevance for self-attention: (layers, heads, keys, keys) x2 -> R (keys, keys).

    R starts as the identity; for each layer in order, Abar = mean over heads of the positive part of
    grad ⊙ attention, and R <- R + Abar @ R. Row i of R: how much token i at the output draws on each input.
    """
    attention = np.asarray(attention, np.float64)
    grad = np.asarray(grad, np.float64)
    relevance = np.eye(attention.shape[-1])
    for layer in range(attention.shape[0]):
        abar = np.clip(grad[layer] * attention[layer], 0.0, None).mean(axis=0)  # (keys, keys)
        relevance = relevance + abar @ relevance
    return relevance


def grad_attention_map(analysis: StepAnalysis) -> dict[str, np.ndarray]:
    """Gradient-weighted attention relevance of the readout rows (mean over readouts)."""
    relevance = gradient_relevance(analysis.attention, analysis.grad_attention)
    return _readout_maps(relevance[analysis.tokens.readout_index].mean(axis=0), analysis.tokens)


def patch_sums(pixels: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """pixels (H, W) -> (rows, cols) sums over each patch (proportional coordinates, as upsample_map)."""
    height, width = pixels.shape
    ry = patch_index(height, rows)
    cx = patch_index(width, cols)
    patch = (ry[:, None] * cols + cx[None, :]).ravel()
    return np.bincount(patch, weights=np.asarray(pixels, np.float64).ravel(), minlength=rows * cols).reshape(rows, cols)


def saliency_map(analysis: StepAnalysis) -> dict[str, np.ndarray]:
    """|dS/dpixels| of the current frame, summed over channels and over each patch's pixels."""
    out = {}
    for _, key, r, c in analysis.tokens.image_groups:
        grad = np.abs(analysis.grad_images[key][-1]).sum(axis=-1)  # (H, W) current frame
        out[key] = patch_sums(grad, r, c)
    return out


def random_map(analysis: StepAnalysis, seed) -> dict[str, np.ndarray]:
    """Uniform random scores per patch from `seed` (an int or a sequence of ints; the control: a ranking that
    knows nothing)."""
    rng = np.random.default_rng(seed)
    return {key: rng.random((r, c)) for _, key, r, c in analysis.tokens.image_groups}


def parse_methods(spec: str | tuple[str, ...] | list[str], layers: int) -> tuple[str, ...]:
    """'attention,rollout,grad-attention,saliency' -> canonical names; 'attention' means every layer
    ('attention:0', ..., 'attention:L-1'); 'attention:2' one layer; 'random' is always added."""
    items = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec) if s.strip()]
    out: list[str] = []
    for item in items:
        base, _, layer = item.partition(":")
        if base not in BASE_METHODS:
            raise ValueError(f"unknown attribution method {item!r}; use {', '.join(BASE_METHODS)} "
                             "(attention:LAYER for one layer)")
        if METHODS[base].layered:
            if layer:
                index = _layer_index(layer, layers)
                names = [f"{base}:{index}"]
            else:
                names = [f"{base}:{i}" for i in range(layers)]
        elif layer:
            raise ValueError(f"{base} takes no layer (got {item!r}); only attention:LAYER does")
        else:
            names = [base]
        out += [n for n in names if n not in out]
    out += [name for name, m in METHODS.items() if m.control and name not in out]
    return tuple(out)


def _layer_index(text: str, layers: int) -> int:
    try:
        index = int(text)
    except ValueError:
        raise ValueError(f"attention layer must be an integer, got {text!r}") from None
    if not -layers <= index < layers:
        raise ValueError(f"attention layer {index} is outside the model's {layers} layers (0..{layers - 1})")
    return index % layers


def occlusion_map(analysis: StepAnalysis) -> dict[str, np.ndarray]:
    """The single-patch deletion changes `analyse(step, occlusion=True)` computed."""
    if analysis.occlusion is None:
        raise ValueError("occlusion needs analyse(step, occlusion=True) (one forward pass per patch)")
    return {k: np.asarray(v, np.float64) for k, v in analysis.occlusion.items()}


@dataclass(frozen=True)
class Method:
    """One attribution method of the table: `fn(analysis, layer, seed) -> {obs key: (rows, cols)}` (layer: the text
    after "attention:", "" for none) and what `analyse` must compute for it."""

    name: str
    fn: Callable
    default: bool  # in DEFAULT_METHODS (what --attribution and --faithfulness-every compute unless told)
    gradients: bool = False  # reads the backward pass (dS/dA, dS/dpixels)
    occlusion: bool = False  # reads one forward pass per patch (costly on large grids)
    layered: bool = False  # takes :LAYER (attention:2)
    control: bool = False  # the random control every method is measured against (always computed)


# The attribution methods, in the order they are listed and drawn (a new method is one row and one function).
METHODS: dict[str, Method] = {m.name: m for m in (
    Method("attention", lambda a, layer, seed: attention_map(a, int(layer) if layer else -1), True, layered=True),
    Method("rollout", lambda a, layer, seed: rollout_map(a), True),
    Method("grad-attention", lambda a, layer, seed: grad_attention_map(a), True, gradients=True),
    Method("saliency", lambda a, layer, seed: saliency_map(a), True, gradients=True),
    Method("occlusion", lambda a, layer, seed: occlusion_map(a), False, occlusion=True),
    Method("random", lambda a, layer, seed: random_map(a, seed), False, control=True),
)}
BASE_METHODS = tuple(METHODS)
DEFAULT_METHODS = ",".join(name for name, m in METHODS.items() if m.default)  # attention,rollout,grad-attention,saliency


def base_of(method: str) -> str:
    """"attention:2" -> "attention"."""
    return method.partition(":")[0]


def needs_gradients(methods) -> bool:
    """Whether any of `methods` (names, with or without :LAYER) reads the backward pass."""
    return any(METHODS[base_of(m)].gradients for m in methods if base_of(m) in METHODS)


def needs_occlusion(methods) -> bool:
    """Whether any of `methods` reads the per-patch deletion passes (`analyse(..., occlusion=True)`)."""
    return any(METHODS[base_of(m)].occlusion for m in methods if base_of(m) in METHODS)


def display_rank(base: str) -> int:
    """Where a method stands in tables and figures: the maps in table order, then the random control, then the
    occlusion reference (and a name not in the table)."""
    maps = [name for name, m in METHODS.items() if not (m.control or m.occlusion)]
    if base in maps:
        return maps.index(base)
    return len(maps) if base in METHODS and METHODS[base].control else len(maps) + 1


def attribute(analysis: StepAnalysis, method: str, seed=0) -> dict[str, np.ndarray]:
    """One method by name (see the module docstring) -> {obs key: (rows, cols)} scores (higher = more used)."""
    base, _, layer = method.partition(":")
    if base not in METHODS:
        raise ValueError(f"unknown attribution method {method!r}; use {', '.join(BASE_METHODS)}")
    return METHODS[base].fn(analysis, layer, seed)


def attribute_all(analysis: StepAnalysis, methods: tuple[str, ...], seed: int = 0) -> dict[str, dict[str, np.ndarray]]:
    """{method: {obs key: (rows, cols)}} for every method name."""
    return {m: attribute(analysis, m, seed) for m in methods}


# ------------------------------------------------------------------------------------------- the Octo model


class OctoFunctions:
    """StepFunctions of one Octo model (jitted once per model and input shape; no state beyond the compiled code).

    `at(observations, task, rng, params=None)` takes what `model.sample_actions` takes with batch 1 (uint8 images at
    the model's sizes, a batch-1 task from `create_task`, one rng key) and returns the step's StepFunction; `params`
    (a tree of the model's structure, e.g. with re-drawn weights: harness.analysis.sanity) replaces the model's own
    weights without compiling again.
    `head_mask` (layers, heads) of 0/1 multiplies each head's attention output (an ablation); None: none.
    """

    def __init__(self, model):
        from harness.octo.network import OctoTransformer

        self.model = model
        self.params = model._inference_params
        self.module = OctoTransformer(model.config, capture_rows=None)
        cfg = model.config.transformer
        self.layers, self.heads = int(cfg.num_layers), int(cfg.num_heads)
        self._fn = jax.jit(self._apply)
        self._batch = jax.jit(jax.vmap(self._apply_actions, in_axes=(None, 0, None, None, None, None, None)))

    def _perturbations(self, perturbation: jax.Array, batch: int = 1) -> dict:
        blocks = {f"encoderblock_{i}": {"MultiHeadDotProductAttention_0": {"weights": jnp.broadcast_to(
            perturbation[i][None], (batch, *perturbation.shape[1:]))}} for i in range(self.layers)}
        return {"BlockTransformer_0": {"Transformer_0": blocks}}

    def _run(self, params, images, obs, task, encoding, pad, rng, perturbation):
        o = dict(obs)
        o.update({k: v[None] for k, v in images.items()})
        variables = {"params": params["octo_transformer"], "perturbations": self._perturbations(perturbation)}
        out = self.module.apply(variables, o, task, encoding, pad)
        actions = self.model.head_actions(params["heads_action"], out, rng[None], None)[0]
        return actions, out["attention"][0]

    def _apply(self, params, images, obs, task, encoding, pad, rng, perturbation):
        return self._run(params, images, obs, task, encoding, pad, rng, perturbation)

    def _apply_actions(self, params, images, obs, task, encoding, pad, rng):
        o = dict(obs)
        o.update({k: v[None] for k, v in images.items()})
        out = self.module.apply({"params": params["octo_transformer"]}, o, task, encoding, pad)
        return self.model.head_actions(params["heads_action"], out, rng[None], None)[0]

    def at(self, observations: Mapping, task: Mapping, rng, params=None) -> StepFunction:
        model = self.model
        params = self.params if params is None else params
        obs, pad = model._prepare_observations(observations)
        if pad.shape[0] != 1:
            raise ValueError(f"attribution takes one example (batch 1); got batch {pad.shape[0]}")
        task_in, encoding = model._prepare_task(task, 1)
        rng = jnp.asarray(rng)
        keys = [k for k in model.image_sizes if k in obs]
        images = {k: np.asarray(obs[k][0], np.float32) for k in keys}
        rest = {k: v for k, v in obs.items() if k not in keys}
        tokens = model._token_map(model._layout(obs, encoding))

        def fn(imgs, perturbation):
            return self._fn(params, imgs, rest, task_in, encoding, pad, rng, perturbation)

        def batch(imgs, chunk: int = 32):
            n = len(next(iter(imgs.values())))
            out = []
            for i in range(0, n, chunk):  # fixed chunk size: one compiled shape
                part = {k: np.asarray(v[i:i + chunk], np.float32) for k, v in imgs.items()}
                m = len(next(iter(part.values())))
                if m < chunk:
                    part = {k: np.concatenate([v, np.repeat(v[:1], chunk - m, axis=0)]) for k, v in part.items()}
                out.append(np.asarray(self._batch(params, part, rest, task_in, encoding, pad, rng))[:m])
            return np.concatenate(out)

        return StepFunction(fn=fn, batch=batch, images=images, tokens=tokens,
                            shape=(self.layers, self.heads, tokens.num_keys))


# ------------------------------------------------------------------------------------------- in a run


class Probe:
    """What a run with `--attribution` / `--faithfulness-every` computes at an inference step, for one model.

    `__call__(observations, task, rng, seed, step)` (batch-1 inputs as `sample_actions` takes them) returns
    {"maps": {method: {obs key: (rows, cols) float32}}, "faithfulness": [rows of step_faithfulness] (only
    every `every`-th step; [] otherwise), "seconds": wall time}. The random map is seeded by (seed, step).
    """

    def __init__(self, model, methods: str | None, every: int = 0, fill: str = "mean"):
        from harness.measures.faithfulness import FILLS

        if fill not in FILLS:
            raise ValueError(f"unknown faithfulness fill {fill!r}; use one of {', '.join(FILLS)}")
        self.functions = OctoFunctions(model)
        self.methods = parse_methods(methods or DEFAULT_METHODS, self.functions.layers)
        self.every = int(every)
        self.fill = fill
        self.gradients = needs_gradients(self.methods)

    def __call__(self, observations: Mapping, task: Mapping, rng, seed: int, step: int) -> dict:
        import time

        from harness.measures.faithfulness import step_faithfulness

        start = time.perf_counter()
        fn = self.functions.at(observations, task, rng)
        analysis = analyse(fn, gradients=self.gradients, occlusion=needs_occlusion(self.methods))
        maps = {m: attribute(analysis, m, seed=[int(seed), int(step)]) for m in self.methods}
        rows = []
        if self.every > 0 and step % self.every == 0:
            rows = step_faithfulness(fn.batch, fn.images, analysis.actions, maps, fill=self.fill,
                                     seed=[int(seed), int(step), 1])
        maps = {m: {k: v.astype(np.float32) for k, v in by.items()} for m, by in maps.items()}
        return {"maps": maps, "faithfulness": rows, "seconds": time.perf_counter() - start}


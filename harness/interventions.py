"""Closed-loop interventions: change what the policy sees (mask patches) or computes (ablate heads) at every step.

An intervention is part of a run's protocol (`PolicyConfig.intervention`, a spec string), so it is recorded,
fingerprinted and compared like any other setting; `octo-harness compare` pairs an intervention run with a
plain run of the same seeds. Specs (K patches per camera; CAMERA an observation key, default every camera the
model reads; METHOD an attribution method of harness.measures.attribution, LAYER for `attention`):

  mask-top:K:METHOD[:LAYER][@CAMERA]     the K patches the method ranks highest on this step's unmasked frame
  mask-bottom:K:METHOD[:LAYER][@CAMERA]  the K it ranks lowest
  mask-random:K[@CAMERA]                 K patches drawn at random (seeded by the episode seed and step)
  mask-all[@CAMERA]                      every patch of the camera (the whole frame)
  ablate-heads:L:H[,L:H...]              the output of head H of layer L zeroed (its slice of the out projection)

Masked patches take the frame's per-channel mean (as the open-loop deletion's "mean" fill), at the model's
image size, on the current frame only; the masked frame is what enters the history window, so with a window
> 1 earlier frames stay as the policy saw them. The ranking of mask-top/-bottom comes from the same window
with the current frame unmasked, and the policy's own rng for that step.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import jax
import numpy as np

from harness.measures import attribution as A
from harness.measures.faithfulness import baseline_image, compose, first_k, ranking

KINDS = ("mask-top", "mask-bottom", "mask-random", "mask-all", "ablate-heads")
USAGE = ("use mask-top:K:METHOD[:LAYER][@CAMERA], mask-bottom:K:METHOD[:LAYER][@CAMERA], mask-random:K[@CAMERA], "
         "mask-all[@CAMERA] or ablate-heads:L:H[,L:H...]")


@dataclass(frozen=True)
class Intervention:
    kind: str
    k: int = 0  # patches per camera (mask-top/-bottom/-random)
    method: str | None = None  # attribution method (mask-top/-bottom), e.g. "attention:2", "saliency"
    camera: str | None = None  # observation key; None = every camera
    heads: tuple[tuple[int, int], ...] = ()  # (layer, head) pairs (ablate-heads)

    @property
    def masks(self) -> bool:
        return self.kind.startswith("mask-")

    def spec(self) -> str:
        """The canonical spec string (what the protocol records)."""
        at = f"@{self.camera}" if self.camera else ""
        if self.kind == "ablate-heads":
            return "ablate-heads:" + ",".join(f"{layer}:{head}" for layer, head in self.heads)
        if self.kind == "mask-all":
            return f"mask-all{at}"
        if self.kind == "mask-random":
            return f"mask-random:{self.k}{at}"
        return f"{self.kind}:{self.k}:{self.method}{at}"


def parse_intervention(spec: str) -> Intervention:
    """A spec string -> Intervention (syntax only; `check` tests it against a model). One-line ValueError."""
    text = str(spec).strip()
    body, _, camera = text.partition("@")
    camera = camera.strip() or None
    kind, _, rest = body.partition(":")
    if kind not in KINDS:
        raise ValueError(f"unknown intervention {text!r}; {USAGE}")
    if kind == "ablate-heads":
        if camera:
            raise ValueError(f"ablate-heads takes no @CAMERA (got {text!r})")
        pairs = []
        for item in rest.split(","):
            layer, _, head = item.partition(":")
            try:
                pair = (int(layer), int(head))
            except ValueError:
                raise ValueError(f"intervention {text!r}: heads are LAYER:HEAD pairs, e.g. ablate-heads:0:1,2:3") from None
            if min(pair) < 0:
                raise ValueError(f"intervention {text!r}: layer and head indices are >= 0")
            if pair not in pairs:
                pairs.append(pair)
        return Intervention("ablate-heads", heads=tuple(sorted(pairs)))
    if kind == "mask-all":
        if rest:
            raise ValueError(f"mask-all takes no K (got {text!r}); mask-all[@CAMERA]")
        return Intervention("mask-all", camera=camera)
    count, _, method = rest.partition(":")
    try:
        k = int(count)
    except ValueError:
        raise ValueError(f"intervention {text!r}: K must be a number of patches; {USAGE}") from None
    if k < 1:
        raise ValueError(f"intervention {text!r}: K must be >= 1")
    if kind == "mask-random":
        if method:
            raise ValueError(f"mask-random takes no METHOD (got {text!r}); mask-random:K[@CAMERA]")
        return Intervention(kind, k=k, camera=camera)
    if not method:
        raise ValueError(f"intervention {text!r} needs a METHOD; {USAGE}")
    base, _, layer = method.partition(":")
    if base not in A.METHODS or A.METHODS[base].control:
        names = [f"{n}[:LAYER]" if m.layered else n for n, m in A.METHODS.items() if not m.control]
        raise ValueError(f"intervention {text!r}: unknown method {method!r}; use {', '.join(names[:-1])} or {names[-1]} "
                         "(mask-random:K for random patches)")
    if not A.METHODS[base].layered and layer:
        raise ValueError(f"intervention {text!r}: only attention takes a layer")
    if base == "attention" and layer:
        try:
            int(layer)
        except ValueError:
            raise ValueError(f"intervention {text!r}: the attention layer must be an integer") from None
    return Intervention(kind, k=k, method=method if base != "attention" or layer else "attention:-1", camera=camera)


def canonical(spec: str | None) -> str | None:
    return None if spec is None else parse_intervention(spec).spec()


class Intervener:
    """Applies one Intervention for one model: `model_for_inference()` (ablated heads) and `mask(...)` per request."""

    def __init__(self, model, intervention: Intervention):
        self.model = model
        self.intervention = intervention
        self.check(model)
        self._functions = A.OctoFunctions(model) if intervention.kind in ("mask-top", "mask-bottom") else None
        self._needs_gradient = A.needs_gradients([intervention.method or ""])

    def check(self, model) -> None:
        """One-line ValueError when the intervention does not fit the model (layers, heads, cameras)."""
        iv = self.intervention
        cfg = model.config.transformer
        for layer, head in iv.heads:
            if layer >= cfg.num_layers or head >= cfg.num_heads:
                raise ValueError(f"--intervene {iv.spec()}: head {layer}:{head} is outside the model's {cfg.num_layers} "
                                 f"layers x {cfg.num_heads} heads")
        if iv.camera is not None and iv.camera not in model.image_sizes:
            raise ValueError(f"--intervene {iv.spec()}: the model reads no camera {iv.camera!r}; "
                             f"its cameras: {', '.join(model.image_sizes)}")
        if iv.k:
            tokens = model.token_map()
            for camera in [iv.camera] if iv.camera else list(model.image_sizes):
                rows, cols = tokens.grid(tokens.camera_group(camera))
                if iv.k > rows * cols:
                    raise ValueError(f"--intervene {iv.spec()}: K={iv.k} is more than the {rows * cols} patches "
                                     f"({rows}x{cols}) of camera {camera}; choose K <= {rows * cols} (mask-all"
                                     f"{'@' + camera if iv.camera else ''} masks every patch)")
        if iv.method and iv.method.startswith("attention:"):
            layer = int(iv.method.split(":")[1])
            if not -cfg.num_layers <= layer < cfg.num_layers:
                raise ValueError(f"--intervene {iv.spec()}: layer {layer} is outside the model's {cfg.num_layers} layers")

    def model_for_inference(self):
        """The model itself, or a shallow copy whose ablated heads' out-projection slices are zero."""
        if not self.intervention.heads:
            return self.model
        params = jax.tree.map(lambda x: x, self.model._inference_params)  # new containers, same leaves
        blocks = params["octo_transformer"]["BlockTransformer_0"]["Transformer_0"]
        for layer, head in self.intervention.heads:
            out = blocks[f"encoderblock_{layer}"]["MultiHeadDotProductAttention_0"]["out"]
            out["kernel"] = np.asarray(out["kernel"]).copy()
            out["kernel"][head] = 0.0  # (heads, head_dim, D): this head's contribution to the block output
        ablated = copy.copy(self.model)
        ablated._inference_params = params
        return ablated

    def mask(self, observation: dict, task: dict, seed: int, step: int, rng) -> dict[str, np.ndarray]:
        """{obs key: (H, W, 3) uint8} the current frames as the policy will see them (only cameras that change).

        observation: the batch-1 window as sample_actions takes it (images (1, window, H, W, 3) uint8);
        task: batch-1 task dict; rng: this step's key (for mask-top/-bottom's attribution).
        """
        iv = self.intervention
        if not iv.masks:
            return {}
        cameras = [iv.camera] if iv.camera else list(self.model.image_sizes)
        scores = None
        if self._functions is not None:
            step_fn = self._functions.at(observation, task, rng)
            analysis = A.analyse(step_fn, gradients=self._needs_gradient, occlusion=A.needs_occlusion([iv.method or ""]))
            scores = A.attribute(analysis, iv.method)
        out = {}
        for key in cameras:
            frame = np.asarray(observation[key][0, -1])
            tokens_grid = self._grid(key)
            n = tokens_grid[0] * tokens_grid[1]
            if iv.kind == "mask-all":
                chosen = np.ones(n, bool)
            elif iv.kind == "mask-random":
                order = np.random.default_rng([seed, step, 0x5EED]).permutation(n)
                chosen = first_k(order, [min(iv.k, n)])[0]
            else:
                order = ranking(scores[key])
                if iv.kind == "mask-bottom":
                    order = order[::-1]
                chosen = first_k(order, [min(iv.k, n)])[0]
            base = baseline_image(frame.astype(np.float32), "mean")
            masked = compose(frame.astype(np.float32), base, chosen.reshape(1, *tokens_grid))[0]
            out[key] = np.clip(np.rint(masked), 0, 255).astype(np.uint8)
        return out

    def _grid(self, key: str) -> tuple[int, int]:
        tokens = self.model.token_map()
        return tokens.grid(tokens.camera_group(key))

"""The readout-features probe (--readout-features-every N): at every N-th inferred step, the embedding the action head
reads: the transformer's readout tokens of the current (last) timestep, pooled as the head pools them (the mean of
the readout tokens, or the head's MAP pooling), one vector of the model's width (128 floats for the robosuite
reference, 384 for octo-small).

It is computed by a second compiled pass of the backbone on the same inputs (the model the policy infers with, the
intervened one under --intervene), never by the call that produced the actions: the executed actions stay
bit-identical to a run without the probe. The due requests of one batched call go through one pass, padded to the
inference's batch shape (one compiled shape).

Payload: {"features": (width,) float32}. Files: readout_features.npz (`.sink`: step (n,) int32, features (n, width)
float16); read back by `.reader`.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from harness.options import option
from harness.probes.registry import Probe, ProbeContext


@dataclass(frozen=True)
class ReadoutFeaturesOptions:
    """The readout-features probe's options (fields of harness.policy.PolicyConfig)."""

    # the pooled readout embedding the action head reads, every N-th inferred step, by a second forward pass
    readout_features_every: int = option(
        0, "--readout-features-every", "the embedding the action head reads (the readout tokens of the current step, "
        "pooled as the head pools them) every N-th inferred step, by a second forward pass that leaves the actions "
        "unchanged, in readout_features.npz (float16)", default_text="{} = never", type=int, file=(int,),
        metavar="N", sparse=True)

    def check(self) -> None:
        """Validate the field on the assembled PolicyConfig; a ValueError names the flag."""
        every = self.readout_features_every
        if isinstance(every, bool) or not isinstance(every, int) or every < 0:
            raise ValueError(f"--readout-features-every must be an integer >= 0 (0 = never), got {every!r}")


class ReadoutFeatures:
    """The jitted second pass of one model: `(model, observations, tasks)` (batch inputs as `sample_actions` takes
    them) -> (batch, width) float32, the pooled readout embedding of the last timestep (what `OctoModel.head_actions`
    hands the head). It keeps the model's configuration, not the model (the cache below is weak on the model)."""

    def __init__(self, config):
        import jax

        from harness.octo.network import OctoTransformer

        self.head = config.action_head
        self.module = OctoTransformer(config, capture_rows=())  # no attention copied out
        self._fn = jax.jit(self._apply)

    def _apply(self, params, obs, task, encoding, pad):
        from harness.octo.heads import pool_readouts

        out = self.module.apply({"params": params["octo_transformer"]}, obs, task, encoding, pad)
        tokens, mask = out["groups"][self.head.readout_key]
        return pool_readouts(params["heads_action"], self.head, tokens, mask)[:, -1]  # (batch, width)

    def __call__(self, model, observations, tasks) -> np.ndarray:
        obs, pad = model._prepare_observations(observations)
        task_in, encoding = model._prepare_task(tasks, pad.shape[0])
        return np.asarray(self._fn(model._inference_params, obs, task_in, encoding, pad), np.float32)


_COMPILED: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()  # model -> its ReadoutFeatures (one compile)


def readout_features(model) -> ReadoutFeatures:
    """The second pass of `model`, made once per model object while it lives (every inference of it shares one
    compiled function; an intervened copy of a model is another object)."""
    if model not in _COMPILED:
        _COMPILED[model] = ReadoutFeatures(model.config)
    return _COMPILED[model]


class ReadoutFeaturesProbe(Probe):
    name = "readout_features"
    option = "readout_features_every"
    options = ReadoutFeaturesOptions
    sink = ".sink:ReadoutArrays"
    reader = ".reader"

    def __init__(self, context: ProbeContext):
        super().__init__(context)
        self.features = readout_features(context.model)

    @classmethod
    def every(cls, config) -> int:
        return int(config.readout_features_every)

    def run(self, batch, context):
        requests = [item.request for item in batch]
        size = context.batch_size
        out = []
        for i in range(0, len(requests), size):
            part = requests[i:i + size]
            observations, tasks, _ = context.inputs(part + [part[0]] * (size - len(part)))
            out.extend(self.features(context.model, observations, tasks)[:len(part)])
        return [{"features": features} for features in out]

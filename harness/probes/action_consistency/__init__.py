"""The action-consistency probe (--action-consistency, --action-samples K): at every inferred step, how much the new
action chunk disagrees with what the episode's earlier chunks planned for the same future steps, in the action
space's units (harness.probes.action_consistency.measure); with K > 0 on a head that samples (diffusion), also the
spread of K more chunks drawn from the same inputs with other rng keys.

Where it is computed. The disagreement needs the episode's earlier chunks, which the batched inference never keeps:
it is stateless and serves many episodes (--workers, Ray replicas, a policy server), so the chunks of one episode
reach it in no fixed place. It is computed by the probe's sink (`.sink`), on the env side, from the chunks the step
records carry (StepRecord.actions_predicted, inferred), in the episode writer's thread: no extra inference, nothing
in the control loop, and the same numbers `measure.episode` computes from any run's actions.npz. The inference side
runs only the K extra draws (one padded call of the batch shape per `batch_size` draws; their actions are discarded);
with K = 0 its payload is the empty marker {} that tells the sink the step is probed.

Payload (inference side): {} or, with K > 0, {"samples": K, "spread": float, "spread_dims": (dim,) float32}. Files:
action_consistency.npz (`.sink`), read back by `.reader`.

Sampling again is refused, in one line naming the fix, for a deterministic head (an L1 or MSE head draws the same
chunk from every key), when the inference is made: before any episode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from harness.options import option
from harness.probes.registry import Probe, ProbeContext


@dataclass(frozen=True)
class ActionConsistencyOptions:
    """The action-consistency probe's options (fields of harness.policy.PolicyConfig)."""

    # disagreement of each inferred chunk with the earlier chunks' plans for the same steps (no extra inference)
    action_consistency: bool = option(
        False, "--action-consistency", "record at every inferred step how much the new action chunk disagrees with "
        "what the earlier chunks planned for the same steps (mean absolute difference in the action space's units, "
        "per chunk age, translation / rotation / gripper apart), in action_consistency.npz; no extra inference",
        file=(bool,), action="store_true", convert=bool, sparse=True)
    # sampling heads (diffusion): K more chunks from the same inputs with other rng keys, and their spread
    action_samples: int = option(
        0, "--action-samples", "with --action-consistency on a head that samples (diffusion): draw K more chunks from "
        "the same inputs with other rng keys at every inferred step and record their spread (K extra inferences a "
        "step; refused for a deterministic L1 head)", default_text="{} = none", type=int, file=(int,), metavar="K",
        sparse=True)

    def check(self) -> None:
        """Validate the fields on the assembled PolicyConfig; a ValueError names the flag."""
        k = self.action_samples
        if isinstance(k, bool) or not isinstance(k, int) or k < 0:
            raise ValueError(f"--action-samples must be an integer >= 0 (0 = none), got {k!r}")
        if k and not self.action_consistency:
            raise ValueError("--action-samples needs --action-consistency (e.g. --action-consistency --action-samples 8)")


def samples_error(model, samples: int) -> str | None:
    """The one line refusing K extra draws from a model whose head does not sample; None when they are fine."""
    from harness.octo.config import DiffusionHeadConfig

    head = getattr(getattr(model, "config", None), "action_head", None)
    if samples and not isinstance(head, DiffusionHeadConfig):
        return (f"--action-samples {samples}: the model's action head is deterministic (an L1/MSE head: every rng "
                f"key gives the same chunk), so there is no spread to sample; drop --action-samples "
                f"(--action-consistency alone measures the chunks' disagreement)")
    return None


class ActionConsistencyProbe(Probe):
    name = "action_consistency"
    option = "action_consistency"
    options = ActionConsistencyOptions
    sink = ".sink:ConsistencyArrays"
    reader = ".reader"

    @classmethod
    def in_inference(cls, config) -> bool:
        """Only the K extra draws run in the policy's inference; the disagreement is the sink's, for any policy."""
        return bool(config.action_samples)

    @classmethod
    def inference_flag(cls, config) -> str:
        return f"--action-samples {config.action_samples}"

    def __init__(self, context: ProbeContext):
        super().__init__(context)
        self.samples = int(context.config.action_samples)
        error = samples_error(context.model, self.samples)
        if error is not None:
            raise ValueError(error)

    def run(self, batch, context):
        if not self.samples:
            return [{} for _ in batch]
        from harness.probes.action_consistency.measure import spread

        drawn = self.draw([item.request for item in batch], context)  # (items, K, H, d)
        out = []
        for item, extra in zip(batch, drawn):
            found = spread(np.concatenate([np.asarray(item.chunk, np.float32)[None], extra]))
            out.append({"samples": self.samples, "spread": found["spread"],
                        "spread_dims": found["spread_dims"].astype(np.float32)})
        return out

    def draw(self, requests: list, context: ProbeContext) -> np.ndarray:
        """(len(requests), K, H, d) float32: K chunks per request from its inputs, the k-th (k = 1..K) with the key
        fold_in(the step's key, k), in calls of the compiled batch shape (padded; padding discarded)."""
        import jax

        k, size = self.samples, context.batch_size
        jobs = [(request, draw) for request in requests for draw in range(1, k + 1)]
        chunks = []
        for i in range(0, len(jobs), size):
            part = jobs[i:i + size]
            padded = part + [part[0]] * (size - len(part))
            observations, tasks, keys = context.inputs([request for request, _ in padded])
            keys = np.stack([np.asarray(jax.random.fold_in(key, draw)) for key, (_, draw) in zip(keys, padded)])
            actions, _ = context.sample(observations, tasks, keys)
            chunks.append(np.asarray(actions, np.float32)[:len(part)])
        chunks = np.concatenate(chunks)
        return chunks.reshape(len(requests), k, *chunks.shape[1:])

"""The policy's options: `CorePolicyConfig` (how actions are executed, unnormalised and sampled) and `PolicyConfig`,
the one frozen dataclass assembled from it and every registered probe's options (harness.probes.registry), whose
fields are the `run` flags, the protocol's "policy" block and the docs' option table. harness.policy runs it."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from harness.octo.diffusion import SAMPLERS
from harness.octo.normalization import NORMALIZATIONS
from harness.options import option, record
from harness.probes.registry import measuring_fields, option_classes

MAX_INFERENCE_BATCH = 256  # a larger compiled batch only costs memory: no machine here gains from it


@dataclass(frozen=True)
class CorePolicyConfig:
    """The policy's own options: how actions are executed, unnormalised and sampled. `PolicyConfig` adds every
    registered probe's options (harness.probes.registry) to these."""

    execution: str = option("temporal_ensemble", "--execution", "", file=(str,),
                            choices=("temporal_ensemble", "receding_horizon"),
                            doc="`temporal_ensemble` (infer every step, average overlapping chunk predictions) or "
                                "`receding_horizon` (execute `--receding-steps` actions of each chunk) [temporal_ensemble]")
    # actions executed per inference when execution == "receding_horizon"; the temporal ensemble executes one
    # action per inference, so it records 1
    receding_steps: int = option(4, "--receding-steps", "actions executed per inference (receding horizon)",
                                 type=int, file=(int,))
    # temporal ensemble: weight exp(-w * age_rank), 0 = plain average (Octo's default)
    ensemble_weight: float = option(0.0, "--ensemble-weight", "temporal ensemble weight exp(-w*i); 0 = mean",
                                    type=float, file=(int, float),
                                    doc="temporal ensemble: of the overlapping predictions for this step, the i-th "
                                        "oldest (i = 0 the oldest) weighs exp(-w·i); 0 is the plain mean, Octo's "
                                        "default; a finite number [0]")
    dataset_key: str | None = option(  # unnormalisation statistics key; None = model's default choice
        None, "--dataset-key", "dataset statistics used to unnormalise actions (default: bridge_dataset when present)",
        file=(str,),
        doc="statistics used to unnormalise actions [bridge_dataset when the checkpoint has it; random presets have "
            "no statistics: their actions stay normalised]")
    full_attention: bool = False  # also return (layers, heads, queries, keys) matrices (needed by attention rollout)
    action_normalization: str = option(  # how the head's actions are unnormalised: mean/std | p01/p99 bounds
        "normal", "--action-normalization",
        "how actions are unnormalised: mean/std or p01/p99 bounds", default_text="checkpoint's harness.toml, else {}",
        file=(str,), choices=("normal", "bounds"),
        doc="how the head's actions are unnormalised: mean/std or p01/p99 bounds (see [finetuned checkpoints]"
            "(octo-runtime.md#finetuned-checkpoints-cameras-proprio-action-space-image-convention)) [the checkpoint's "
            "`harness.toml`, else normal]")
    proprio_normalization: str = option(  # low-dim inputs: "normal" | "bounds" | "none" (harness.octo.normalization)
        "normal", "--proprio-normalization", "how proprio inputs are normalised",
        default_text="checkpoint's harness.toml, else {}", file=(str,), choices=("normal", "bounds", "none"))
    sampler: str = option(  # diffusion heads: "latest" (the latest original code, any checkpoint) | "v0.1.0"
        "latest", "--sampler", "diffusion sampling as the latest original Octo code does, or as v0.1.0 did",
        file=(str,), choices=("latest", "v0.1.0"))
    # examples per compiled inference call: every call (sequential, --workers, Ray) is padded to exactly this size, so
    # an example's numbers never depend on what shares its call, the worker count or the load (XLA's results depend
    # on the batch shape; 1 is fastest on a CPU, where one inference already uses every core)
    inference_batch: int = option(
        1, "--inference-batch", "examples per compiled inference call; every call is padded to it, so actions are "
        "bit-identical whatever --workers or the load (part of the protocol; >1 pays on a GPU)", type=int, file=(int,))
    # closed-loop intervention (harness/interventions.py), e.g. "mask-top:4:attention:2"; None = none
    intervention: str | None = option(
        None, "--intervene", "closed-loop intervention at every step (part of the protocol): mask-top:K:METHOD[:LAYER]"
        "[@CAMERA], mask-bottom:K:METHOD[:LAYER][@CAMERA], mask-random:K[@CAMERA], mask-all[@CAMERA], "
        "ablate-heads:L:H[,L:H...] (METHOD: attention, rollout, grad-attention, saliency)",
        file=(str,), metavar="SPEC", sparse=True, field="intervention")
    def check(self) -> None:
        """Validate (and complete) the policy's own fields; a ValueError names the flag."""
        if self.execution not in ("temporal_ensemble", "receding_horizon"):
            raise ValueError(f"unknown execution {self.execution!r}; use 'temporal_ensemble' or 'receding_horizon'")
        if isinstance(self.receding_steps, bool) or not isinstance(self.receding_steps, int) or self.receding_steps < 1:
            raise ValueError(f"--receding-steps must be an integer >= 1, got {self.receding_steps!r}")
        if self.execution == "temporal_ensemble":
            object.__setattr__(self, "receding_steps", 1)
        if not math.isfinite(float(self.ensemble_weight)):
            raise ValueError(f"--ensemble-weight must be a finite number, got {self.ensemble_weight}")
        if self.action_normalization not in ("normal", "bounds"):
            raise ValueError(f"unknown action normalization {self.action_normalization!r}; use 'normal' or 'bounds'")
        if self.proprio_normalization not in NORMALIZATIONS:
            raise ValueError(f"unknown proprio normalization {self.proprio_normalization!r}; use one of {', '.join(NORMALIZATIONS)}")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"unknown sampler {self.sampler!r}; use one of {', '.join(SAMPLERS)}")
        if isinstance(self.inference_batch, bool) or not isinstance(self.inference_batch, int) \
                or not 1 <= self.inference_batch <= MAX_INFERENCE_BATCH:
            raise ValueError(f"--inference-batch must be an integer in 1..{MAX_INFERENCE_BATCH}, got {self.inference_batch!r}")
        if self.intervention is not None:
            from harness.interventions import canonical

            object.__setattr__(self, "intervention", canonical(self.intervention))

    def to_dict(self) -> dict:
        """The fields as plain data; the sparse options only when set (protocols without them keep their hash)."""
        return record(self)

    def describe(self) -> str:
        if self.execution == "receding_horizon":
            return f"receding_horizon:{self.receding_steps}"
        return f"temporal_ensemble:{self.ensemble_weight:g}"


def _assemble_policy_config() -> type:
    """PolicyConfig: CorePolicyConfig's fields, then each registered probe's options (in registration order), one
    frozen dataclass whose __post_init__ runs CorePolicyConfig.check, then each probe's `check`. Its fields are the
    `run` flags, the protocol's "policy" block and the docs' option table, wherever a field is declared."""
    probe_options = option_classes()

    def __post_init__(self) -> None:
        CorePolicyConfig.check(self)
        for options in probe_options:
            options.check(self)

    cls = dataclasses.make_dataclass(
        "PolicyConfig", [], bases=(*reversed(probe_options), CorePolicyConfig), frozen=True,
        namespace={"__post_init__": __post_init__, "__doc__": "How the policy runs and what it measures beside: "
                   "CorePolicyConfig's fields and every registered probe's options (harness.probes.registry)."})
    cls.__module__ = __name__  # pickled by name into spawned workers and Ray
    return cls


PolicyConfig = _assemble_policy_config()


def without_probes(config: "PolicyConfig") -> "PolicyConfig":
    """`config` with every probe that never changes actions turned off (its option fields at their defaults): what
    `regress --drop-probes` and `replay --drop-probes` run of a baseline that measured beside its actions."""
    names = set(measuring_fields())
    defaults = {f.name: f.default for f in dataclasses.fields(PolicyConfig) if f.name in names}
    return dataclasses.replace(config, **defaults)

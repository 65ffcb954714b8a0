"""Records that flow down the pipeline: what a rollout hands to analysis and writers per step.

The rollout fills a `StepRecord` per control step and a `EpisodeMeta` per episode; the writers only
read them. All arrays are numpy (batch index 0 already taken).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from harness.octo.tokens import TokenMap


@dataclass(frozen=True, eq=False)
class StepRecord:
    step: int  # control step index t (0-based)
    frames: dict[str, np.ndarray]  # observation key -> (height, width, 3) uint8, the frame the model saw, shown upright
    # (layers, heads, readouts, keys) float32, post-softmax rows of the last timestep's readouts; None when the policy
    # gives no attention (harness.policies.Capabilities.attention False, e.g. a served policy): the step then has no
    # token map either, and the writers record everything else (frames, actions, rewards, masks, inputs) without
    # attention arrays, panels or measures (harness.outputs.writers)
    readout_attention: np.ndarray | None
    actions_predicted: np.ndarray  # (action_horizon, action_dim) float32, unnormalised chunk predicted at this step
    action_executed: np.ndarray  # (action_dim,) float32, the action sent to the env at this step
    reward: float
    success: bool
    masks: dict[str, dict[str, np.ndarray]] | None = None  # obs key -> {"target": (h, w) bool, "robot": (h, w) bool}, upright
    full_attention: np.ndarray | None = None  # (layers, heads, queries, keys) float32 when requested (attention rollout)
    timings: dict[str, float] = field(default_factory=dict)  # seconds: "simulation", "inference", "enqueue"
    inferred: bool = True  # False when this step executed a stored chunk action (receding horizon): attention is that chunk's
    tokens: TokenMap | None = None  # what each key of the attention is: the map of the very inference that produced it
    policy_inputs: dict[str, np.ndarray] | None = None  # what the policy was fed at this step (PolicyStep.inputs), in the
    # env's image convention: image_* (height, width, 3) uint8 resized, low-dim (dims,) float32
    phase: str | None = None  # the task phase of the state the model saw (envs.phases; None: the task has no phases)
    # the per-step probes' payloads of this step's inference, keyed by probe name (harness.probes: each probe's module
    # says what its payload holds), turned upright as the frames are; {} at steps where no probe ran
    probes: dict = field(default_factory=dict)


@dataclass(frozen=True)
class EpisodeMeta:
    run: str
    task: str
    episode: int
    seed: int
    instruction: str
    model: str  # model source (uri), e.g. "random:octo-small-1.5", "hf://rail-berkeley/octo-small-1.5"
    model_is_random: bool
    dataset_key: str | None
    text_tokenizer: str  # e.g. "t5-base" or "fallback (deterministic hash, NOT t5)"
    execution: str  # e.g. "temporal_ensemble" or "receding_horizon:4"
    extra: dict = field(default_factory=dict)

"""One closed-loop episode: env -> policy -> env, every step handed to a sink as a finished StepRecord.

`rollout` owns no files: it returns an `EpisodeResult` (arrays and numbers) and pushes each
`StepRecord` to `sink` (an EpisodeWriter, or any callable taking a StepRecord), which may do its
work in the background.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from harness.policy import OctoPolicy
from harness.records import StepRecord


@dataclass(frozen=True)
class EpisodeResult:
    success: bool
    steps: int
    total_reward: float
    instruction: str
    actions_clipped: int
    timings: dict[str, float] = field(default_factory=dict)  # seconds summed over steps: simulation, inference, enqueue, step


def rollout(
    env,
    policy: OctoPolicy,
    sink: Callable[[StepRecord], None],
    *,
    seed: int,
    instruction: str | None = None,
    goals: dict[str, np.ndarray] | None = None,
    max_steps: int | None = None,
    on_step: Callable[[int, StepRecord], None] | None = None,
) -> EpisodeResult:
    """Run one episode with `env.reset(seed=seed)`; stops on termination, truncation or `max_steps`.

    The task is the language instruction, or `goals` ({obs key: (height, width, 3) uint8}) when given.
    """
    observation, info = env.reset(seed=seed)
    instruction = instruction or info.get("instruction", "")
    policy.reset(instruction, seed=seed, goals=goals)
    limit = max_steps if max_steps is not None else math.inf
    totals = {"simulation": 0.0, "inference": 0.0, "enqueue": 0.0, "step": 0.0}
    total_reward, success, t = 0.0, False, 0
    while t < limit:
        start = time.perf_counter()
        decision = policy.step(observation)
        after_policy = time.perf_counter()
        next_observation, reward, terminated, truncated, next_info = env.step(decision.action)
        after_sim = time.perf_counter()
        success = bool(next_info.get("success", False))
        total_reward += float(reward)
        record = StepRecord(
            step=t,
            frames={key: observation[key] for key in policy.image_sizes},
            readout_attention=decision.readout_attention,
            actions_predicted=decision.chunk,
            action_executed=np.asarray(decision.action, dtype=np.float32),
            reward=float(reward),
            success=success,
            masks=info.get("masks"),  # masks of `observation`, the frame the model saw
            full_attention=decision.full_attention,
            timings={"inference": decision.inference_seconds, "simulation": after_sim - after_policy},
            inferred=decision.inferred,
        )
        sink(record)
        end = time.perf_counter()
        totals["inference"] += decision.inference_seconds
        totals["simulation"] += after_sim - after_policy
        totals["enqueue"] += end - after_sim
        totals["step"] += end - start
        if on_step is not None:
            on_step(t, record)
        t += 1
        observation, info = next_observation, next_info
        if terminated or truncated:
            break
    return EpisodeResult(
        success=success,
        steps=t,
        total_reward=total_reward,
        instruction=instruction,
        actions_clipped=int(info.get("action_clipped", 0)),
        timings=totals,
    )

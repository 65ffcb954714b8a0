"""One closed-loop episode: env -> policy -> env, every step handed to a sink as a finished StepRecord.

`rollout` owns no files: it returns an `EpisodeResult` (arrays and numbers) and pushes each
`StepRecord` to `sink` (an EpisodeWriter, or any callable taking a StepRecord), which may do its
work in the background.

Image convention: the policy sees the frames exactly as the env gives them (for an env with
image_convention "opengl", upside down, as the model was trained; "rot180", mirrored left to right).
Records are for people and for the attention analysis, so they are upright: frames and masks are
flipped back and the token map's patch rows (opengl) or columns (rot180) are reversed for those
cameras (`TokenMap.with_rows_flipped` / `with_cols_flipped`), so maps, overlays and mask mass all
live in the upright frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from envs.options import to_convention
from harness.policy import ClosedLoopPolicy
from harness.probes import get as get_probe
from harness.records import StepRecord


@dataclass(frozen=True)
class EpisodeResult:
    success: bool
    steps: int
    total_reward: float
    instruction: str
    actions_clipped: int
    timings: dict[str, float] = field(default_factory=dict)  # seconds summed over steps: simulation, inference, enqueue, step
    # the task's phases (envs.phases), None for tasks without a phase function: {"names": [...], "steps": {phase:
    # recorded steps in it}, "furthest": the furthest phase of any state, the final one (after the last step) included}
    phases: dict | None = None
    # what the episode did to the scene, from the simulator state at its end, for envs that say (LiberoEnv's
    # episode_outcome: the object picked); None for the others
    outcome: dict | None = None


def rollout(
    env,
    policy: ClosedLoopPolicy,
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
    policy.check_env(env)  # a model/env mismatch is one line, before the episode starts
    convention = getattr(getattr(env, "unwrapped", env), "image_convention", "upright")
    upright_tokens = _UprightTokens(tuple(policy.image_sizes) if convention != "upright" else (), convention)
    observation, info = env.reset(seed=seed)
    instruction = instruction or info.get("instruction", "")
    policy.reset(instruction, seed=seed, goals=goals)
    limit = max_steps if max_steps is not None else math.inf
    totals = {"simulation": 0.0, "inference": 0.0, "enqueue": 0.0, "step": 0.0}
    total_reward, success, t = 0.0, False, 0
    names = _phase_names(env, info)
    seen_phases = [info.get("phase")]
    while t < limit:
        start = time.perf_counter()
        decision = policy.step(observation, info.get("masks"))  # masks: sent only at the steps of a probe that needs them
        _check_finite(t, decision.action)
        after_policy = time.perf_counter()
        next_observation, reward, terminated, truncated, next_info = env.step(decision.action)
        after_sim = time.perf_counter()
        success = bool(next_info.get("success", False))
        total_reward += float(reward)
        record = _step_record(t, observation, info, decision, float(reward), success, after_sim - after_policy,
                              policy.image_sizes, convention, upright_tokens)
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
        seen_phases.append(info.get("phase"))
        if terminated or truncated:
            break
    outcome = getattr(getattr(env, "unwrapped", env), "episode_outcome", None)
    return EpisodeResult(
        outcome=outcome() if callable(outcome) else None,
        success=success,
        steps=t,
        total_reward=total_reward,
        instruction=instruction,
        actions_clipped=int(info.get("action_clipped", 0)),
        timings=totals,
        phases=_phase_summary(names, seen_phases[:-1], seen_phases),
    )


def _check_finite(t: int, action) -> None:
    """MuJoCo would integrate a NaN action silently: the episode errors instead (FloatingPointError, one line)."""
    if not np.all(np.isfinite(action)):
        raise FloatingPointError(f"step {t}: the policy's action is not finite ({np.asarray(action).tolist()}); "
                                 "the model's weights or dataset statistics hold NaN or inf")


def _step_record(t: int, observation: dict, info: dict, decision, reward: float, success: bool, simulation: float,
                 image_keys, convention: str, upright_tokens: _UprightTokens) -> StepRecord:
    """The record of step `t`: the frames the model saw (`observation`, upright) and their masks, what it decided,
    what the env returned; the token maps and the probes' maps turned upright as the frames are."""
    return StepRecord(
        step=t,
        frames={key: to_convention(observation[key], convention) for key in image_keys},
        readout_attention=decision.readout_attention,
        actions_predicted=decision.chunk,
        action_executed=np.asarray(decision.action, dtype=np.float32),
        reward=reward,
        success=success,
        masks=_upright_masks(info.get("masks"), convention),  # masks of `observation`, the frame the model saw
        full_attention=decision.full_attention,
        timings={"inference": decision.inference_seconds, "simulation": simulation},
        inferred=decision.inferred,
        tokens=upright_tokens(decision.tokens),
        policy_inputs=decision.inputs,
        phase=info.get("phase"),
        probes=_upright_probes(decision.probes, upright_tokens.flipped_keys, convention),
    )


def _phase_names(env, info: dict) -> tuple[str, ...]:
    """The env's task phases in order, () when it has none (or no phase in its info)."""
    if info.get("phase") is None:
        return ()
    from envs.phases import phase_names

    return phase_names(str(info.get("task", "")))


def _phase_summary(names: tuple[str, ...], recorded: list, every: list) -> dict | None:
    """{"names", "steps": {phase: recorded steps}, "furthest"} or None without phases."""
    if not names:
        return None
    reached = [names.index(p) for p in every if p in names]
    return {"names": list(names), "steps": {n: sum(p == n for p in recorded) for n in names},
            "furthest": names[max(reached)] if reached else None}


def _upright_probes(payloads: dict, flipped_keys: tuple[str, ...], convention: str = "opengl") -> dict:
    """{probe name: payload} with each probe's maps of upside-down cameras (image convention "opengl": patch rows
    reversed) or mirrored ones ("rot180": patch columns reversed) upright (`Probe.upright`)."""
    if not payloads or not flipped_keys:
        return payloads
    turn = (lambda v: v[:, ::-1]) if convention == "rot180" else (lambda v: v[::-1])  # noqa: E731
    flip = lambda key, value: turn(value) if key in flipped_keys else value  # noqa: E731
    return {name: get_probe(name).upright(payload, flip) for name, payload in payloads.items()}


def _upright_masks(masks: dict | None, convention: str) -> dict | None:
    """{obs key: {name: (h, w) bool}} in the env's convention -> upright."""
    if masks is None or convention == "upright":
        return masks
    flip = lambda m: None if m is None else to_convention(m, convention)  # noqa: E731
    return {key: {name: flip(m) for name, m in (named or {}).items()} for key, named in masks.items()}


class _UprightTokens:
    """Token map of an inference -> the same with the rows of upside-down cameras reversed (one copy per map)."""

    def __init__(self, flipped_keys: tuple[str, ...], convention: str = "opengl"):
        self.flipped_keys = flipped_keys
        self.convention = convention
        self._last: tuple = (None, None)

    def __call__(self, tokens):
        if tokens is None or not self.flipped_keys:
            return tokens
        if self._last[0] is not tokens:
            flipped = (tokens.with_cols_flipped(self.flipped_keys) if self.convention == "rot180"
                       else tokens.with_rows_flipped(self.flipped_keys))
            self._last = (tokens, flipped)
        return self._last[1]

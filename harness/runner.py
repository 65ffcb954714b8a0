"""Compatibility layer: the `RunConfig` / `run(config)` API of earlier versions, on top of harness.run.

New code uses `harness.run.execute(protocol, out, run_name)` directly (see harness/run/__init__.py). `run`
builds the protocol from a `RunConfig` and executes it without a progress bar; rows' `directory` is relative
to `summary.run_dir` (use `summary.episode_dir(row)`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from envs.options import EnvOptions
from harness.policy import PolicyConfig
from harness.records import StepRecord
from harness.run.driver import RunSummary, execute
from harness.run.protocol import Protocol
from harness.run.settings import normalise_model, resolve_tasks
from harness.run.store import EpisodeRow
from harness.outputs.writers import OutputOptions

__all__ = ["EpisodeRow", "RunConfig", "RunSummary", "run"]


@dataclass(frozen=True)
class RunConfig:
    tasks: tuple[str, ...]
    model: str
    episodes: int = 1
    seed: int = 0  # episode k of every task uses seed + k
    max_steps: int | None = None  # None = the task's own limit
    out_dir: Path = Path("results/runs")
    run_name: str | None = None  # default: <model>_<protocol hash>, so the same config resumes the same run
    instruction: str | None = None  # override the task's default instruction
    masks: bool = True  # ask the env for target/robot masks (attention mass on the target)
    fast_render: bool = False  # no reflections/shadows/anti-aliasing: ~3.6x faster frames, near-identical pixels
    goal_images: Path | None = None  # folder with <obs key>.png goal images (goal-conditioned models)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    outputs: OutputOptions = field(default_factory=OutputOptions)
    env: EnvOptions | None = None  # full env options; when given, masks and fast_render above are ignored

    def protocol(self) -> Protocol:
        env = self.env or EnvOptions(masks=self.masks, fast_render=self.fast_render)
        return Protocol(model=normalise_model(self.model), tasks=resolve_tasks(self.tasks), episodes=self.episodes,
                        seed=self.seed, max_steps=self.max_steps, instruction=self.instruction,
                        goal_images=str(Path(self.goal_images).resolve()) if self.goal_images else None,
                        env=env, policy=self.policy, outputs=self.outputs)


def run(config: RunConfig, *, model=None, on_step: Callable[[str, int, int, StepRecord], None] | None = None,
        overwrite: bool = False) -> RunSummary:
    """Run (or resume) every episode of every task. `model` may be passed in to reuse an already loaded one."""
    step = (lambda job, t, record: on_step(job.task, job.episode, t, record)) if on_step else None
    return execute(config.protocol(), config.out_dir, config.run_name, overwrite=overwrite, model=model,
                   on_step=step, progress=False)

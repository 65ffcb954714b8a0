"""DAgger corrections for the LIBERO-Object reference policy: the checkpoint acts, the state-based expert labels.

The LIBERO counterpart of reference_policies.dagger. The checkpoint runs each LIBERO-Object task as the evaluation
runs it (its harness.toml conventions, fast render) from placements LIBERO's sampler draws with seeds
LIBERO_DAGGER_SEED_BASE + 10_000 * task + k (apart from the demonstrations' 1_000_000 block and never the suite's
stored evaluation states), and `LiberoObjectLabeller` says at every visited state what the expert would do there:
open and back up after a grasp closed beside the object, re-centre when off, carry and release once it holds.
Episodes run in spawned processes in a fixed split of jobs per task, so the data do not depend on the workers.

Resumable: each job is saved into `<out>/jobs/` as it finishes, with the configuration's and checkpoint's
fingerprint, and a later call runs only the jobs not saved there.

Output: `<out>/<suite>_<index>.npz` per task (the layout of reference_policies.demos plus `success`, and `weight`:
`near_weight` for states near the grasp, else 1, the fine-tuning's sampling weight) and
`<out>/summary.json` (per task: episodes, steps, policy successes; seconds; configuration and checkpoint).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from harness.files import atomic_write_json
from reference_policies.dagger import (append_corrections, checkpoint_fingerprint, end_reuse, labelled_episode,
                                      load_labelled_parts, reused_policy_in_env, save_collection, save_labelled_part)
from reference_policies.demos import config_fingerprint, finished_recording, run_saved_jobs
from reference_policies.libero_demos import LIBERO_OBJECT_TASKS, task_file
from reference_policies.libero_expert import LiberoExpertConfig, LiberoObjectLabeller

log = logging.getLogger(__name__)

LIBERO_DAGGER_SEED_BASE = 2_000_000  # placement seeds of task i: 2_000_000 + 10_000 i + k


@dataclass(frozen=True)
class LiberoDaggerConfig:
    tasks: tuple[str, ...] = LIBERO_OBJECT_TASKS
    episodes: int = 6  # per task
    jobs_per_task: int = 2  # fixed split (not the worker count), so the data do not depend on the workers
    max_steps: int = 280  # LIBERO-Object's step limit
    expert: LiberoExpertConfig = field(default_factory=LiberoExpertConfig)  # the labeller's waypoints; fingerprinted
    round: int = 1  # DAgger round: its own block of placement seeds (1000 per round within the task's block)
    # states with the hand within `near_radius` (m) of the grasp point, object not yet held, are drawn `near_weight`
    # times as often in fine-tuning (the grasp is where the policy fails: issue 46)
    near_radius: float = 0.06
    near_weight: float = 3.0

    def __post_init__(self) -> None:
        if self.episodes < self.jobs_per_task or self.max_steps < 1:
            raise ValueError(f"--dagger-episodes must be >= {self.jobs_per_task} per task (one per job) and "
                             "--max-steps >= 1")
        if not 1 <= self.round <= 9 or self.episodes > 1000 or not self.near_weight > 0:
            raise ValueError("a DAgger round is 1..9 with at most 1000 episodes per task and a near-grasp weight > 0")

    def seeds(self, task: str) -> list[int]:
        base = LIBERO_DAGGER_SEED_BASE + 10_000 * int(task.split("/")[1]) + 1_000 * (self.round - 1)
        return [base + k for k in range(self.episodes)]


def _collect_job(args: tuple) -> tuple[str, list[dict]]:
    """Spawned worker: (task, its episodes of seeds `seeds`, each {arrays..., "seed", "success"})."""
    model_dir, config, task, seeds = args
    from envs.libero_tasks import get_libero_task

    env, policy = reused_policy_in_env(model_dir, task, config.max_steps)  # the same for the task's next job
    labeller = LiberoObjectLabeller(get_libero_task(task).targets[0], config=config.expert)
    episodes = []
    try:
        for seed in seeds:
            obs, info = env.reset(seed=seed, options={"initial_state": "sampled"})
            near: list[bool] = []

            def label(o):
                near.append(labeller.near_grasp(env, o, config.near_radius))
                return labeller.act(env, o)

            episode = labelled_episode(env, policy, label, obs, info, seed, config.max_steps)
            episode["weight"] = np.where(near, config.near_weight, 1.0)
            episodes.append(episode)
    except BaseException:
        end_reuse()  # an env left mid-episode by an error is not reused
        raise
    return task, episodes


def collect(model_dir: str | Path, out_dir: str | Path, config: LiberoDaggerConfig = LiberoDaggerConfig(),
            workers: int = 2) -> dict:
    """Run the checkpoint on every task's seeds, label every visited state; write `<out>/<suite>_<index>.npz`."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    jobs = [(str(model_dir), config, task, config.seeds(task)[j::config.jobs_per_task])
            for task in config.tasks for j in range(config.jobs_per_task)]
    start = time.perf_counter()
    fp = fingerprint(config, model_dir)

    def part_of(job) -> Path:  # each finished job is saved at once, so a stop loses only the jobs under way
        return out_dir / "jobs" / f"{task_file(job[2])[:-4]}_{job[3][0]}.npz"

    try:
        for job, (task, episodes) in run_saved_jobs(_collect_job, jobs, workers, part_of, fp, lambda job: len(job[3])):
            success = save_labelled_part(part_of(job), episodes, fp)
            log.info("%s seeds %d..: %d episodes collected, %d successes", task, job[3][0], len(success),
                     success.sum())
    finally:
        end_reuse()  # the env of the jobs run in this process (one worker)
    summary = {}
    for task in config.tasks:
        episodes = load_labelled_parts(part_of(job) for job in jobs if job[2] == task)
        summary[task] = save_collection(out_dir, episodes, task_file(task))
        log.info("%s: %s", task, summary[task])
    summary["seconds"] = time.perf_counter() - start
    summary["config"] = fp
    atomic_write_json(out_dir / "summary.json", summary, exact=True)
    return summary


def fingerprint(config: LiberoDaggerConfig, model_dir: str | Path) -> dict:
    """JSON-able description of a collection: its configuration and the checkpoint that acted."""
    return {**config_fingerprint(config), "checkpoint": checkpoint_fingerprint(model_dir)}


def existing(config: LiberoDaggerConfig, model_dir: str | Path, out_dir: str | Path) -> dict | None:
    """The summary of a finished collection with this configuration and checkpoint in `out_dir`, else None."""
    return finished_recording(out_dir, fingerprint(config, model_dir), tuple(task_file(t)[:-4] for t in config.tasks))


def append_all(demos: dict[str, dict[str, np.ndarray]], out_dir: str | Path,
               tasks: tuple[str, ...]) -> dict[str, dict[str, np.ndarray]]:
    """`demos` with every task's corrections in `out_dir` appended as further episodes of that task."""
    for task in tasks:
        demos = append_corrections(demos, out_dir, task, task_file(task))
    return demos

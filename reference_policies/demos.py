"""Demonstrations from the scripted experts, recorded as the reference policy will see them.

Each step stores what the closed loop feeds the model: the env's default cameras (agentview 256 px,
eye-in-hand 128 px, upright, fast render) resized with the policy's own Lanczos resize to the model's
sizes, the env's `proprio`, and the expert's robosuite OSC_POSE input as the action label. While
recording, Gaussian noise perturbs the *executed* arm input (the label stays the expert's clean action)
so the data covers the small deviations a learned policy makes (DART-style); episodes the expert fails
under noise are dropped and the next seed is used.

Seeds: training episodes of task i use seeds TRAIN_SEED_BASE + 100_000 * i + k (Lift 100000.., Stack
200000.., PickPlaceCan 300000..); evaluation uses seeds 0..EVAL_SEEDS-1, never recorded here.
Recording runs in spawned processes (never fork after rendering); a job's episodes depend only on its
seeds, so the data are identical whatever the number of workers.

Output: one `<task>.npz` per task under the output folder with
  image_primary (n, S, S, 3) uint8, image_wrist (n, W, W, 3) uint8, proprio (n, 8) float32,
  action (n, 7) float32 (label), episode (n,) int32, step (n,) int32, seeds (episodes,) int64,
  lengths (episodes,) int32.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import time
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from harness.files import atomic_write_json, read_json_object, write_atomic
from harness.interrupts import die_with_parent
from reference_policies.experts import EXPERT_TASKS, ExpertConfig, ScriptedExpert

log = logging.getLogger(__name__)

TRAIN_SEED_BASE = 100_000
EVAL_SEEDS = 50  # evaluation seeds 0..49
SEEDS_PER_JOB = 1_000  # seed block reserved for one recording job (dropped episodes use the next seeds)


@dataclass(frozen=True)
class DemoConfig:
    tasks: tuple[str, ...] = EXPERT_TASKS
    # demonstrations per task: the long, least reliable task gets the most (PickPlaceCan 18% with 64 each)
    episodes: tuple[tuple[str, int], ...] = (("Lift", 96), ("Stack", 128), ("PickPlaceCan", 192))
    jobs_per_task: int = 4  # fixed split (not the worker count) so the data do not depend on the workers
    # model input sizes: primary 128 px (8x8 patches of 16 px), wrist 64 px (4x4); TrainConfig.image_sizes matches
    image_sizes: tuple[tuple[str, int], ...] = (("image_primary", 128), ("image_wrist", 64))
    fast_render: bool = True
    noise: float = 0.3  # std of the Gaussian noise added to the executed position input (OSC units)
    max_steps: dict = field(default_factory=lambda: {"Lift": 120, "Stack": 250, "PickPlaceCan": 300})
    expert: ExpertConfig = ExpertConfig()  # part of the fingerprint: a changed expert records afresh

    def episodes_of(self, task: str) -> int:
        return dict(self.episodes)[task]

    def task_seed_base(self, task: str) -> int:
        return TRAIN_SEED_BASE + 100_000 * EXPERT_TASKS.index(task)


def record_episode(env, expert: ScriptedExpert, seed: int, sizes: dict[str, int], noise: float,
                   max_steps: int) -> dict | None:
    """One noisy expert episode; arrays as in the module docstring, or None if the expert failed."""
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    expert.reset(obs, env)
    return noisy_episode(env, obs, lambda o: expert.act(o, env), sizes, noise, rng, max_steps)


def noisy_episode(env, obs: dict, act, sizes: dict[str, int], noise: float, rng: np.random.Generator,
                  max_steps: int, perturb=None, succeeded=None) -> dict | None:
    """From observation `obs`, step `env` with the labels `act(obs)` whose first three (position) entries carry
    Gaussian noise of std `noise` (clipped to [-1, 1]; the stored label stays clean) until success, truncation or
    `max_steps`; the frames resized to `sizes` ({key: side}), proprio and labels -> arrays, or None without success.
    `perturb(executed, label, rng) -> executed`, when given, further changes what is executed after the noise (the
    recovery bursts of reference_policies.libero_demos.Bursts); the label stays the expert's. `succeeded(info)`, when
    given, replaces the env's own success predicate (a swapped instruction's object placed)."""
    from harness.policy import resize_frame

    frames = {k: [] for k in sizes}
    proprio, actions = [], []
    success = False
    for _ in range(max_steps):
        label = act(obs)
        for key, size in sizes.items():
            frames[key].append(resize_frame(obs[key], (size, size)))
        proprio.append(obs["proprio"].astype(np.float32))
        actions.append(label)
        executed = label.copy()
        executed[:3] = np.clip(executed[:3] + noise * rng.standard_normal(3), -1.0, 1.0)
        if perturb is not None:
            executed = perturb(executed, label, rng)
        obs, _, terminated, truncated, info = env.step(executed)
        success = bool(info["success"] if succeeded is None else succeeded(info))
        if success or truncated:
            break
    if not success:
        return None
    out = {k: np.stack(v) for k, v in frames.items()}
    out["proprio"] = np.stack(proprio)
    out["action"] = np.stack(actions).astype(np.float32)
    return out


def _record_job(args: tuple) -> tuple[list[dict], list[int], int]:
    """Spawned worker: `count` successful episodes of `task` from seeds `first_seed`, `first_seed + 1`, ..."""
    task, first_seed, count, config = args
    import envs

    env = envs.make(task, fast_render=config.fast_render, action_space="robosuite",
                    max_episode_steps=config.max_steps[task])
    expert = ScriptedExpert(task, config.expert)
    sizes = dict(config.image_sizes)
    try:
        return successful_episodes(lambda seed: record_episode(env, expert, seed, sizes, config.noise,
                                                               config.max_steps[task]), task, first_seed, count)
    finally:
        env.close()


def successful_episodes(record, task: str, first_seed: int, count: int,
                        seeds_per_job: int = SEEDS_PER_JOB) -> tuple[list[dict], list[int], int]:
    """`record(seed)` (an episode, or None when the expert failed) over seeds from `first_seed` until `count`
    episodes succeeded -> (episodes, their seeds, dropped); an error when the job's seed block runs out."""
    episodes, seeds, dropped = [], [], 0
    for seed in range(first_seed, first_seed + seeds_per_job):
        if len(episodes) == count:
            break
        episode = record(seed)
        if episode is None:
            dropped += 1
        else:
            episodes.append(episode)
            seeds.append(seed)
    if len(episodes) < count:
        raise RuntimeError(f"{task}: the expert failed on too many seeds from {first_seed}")
    return episodes, seeds, dropped


def record_demos(config: DemoConfig, out_dir: str | Path, workers: int = 2) -> dict:
    """Record every task's demonstrations into `out_dir/<task>.npz`; returns a summary per task."""
    return record_tasks(_record_job, config, {t: config.episodes_of(t) for t in config.tasks}, out_dir,
                        lambda task: f"{task}.npz", workers)


def record_tasks(job, config, episodes: dict[str, int], out_dir: str | Path, file_of, workers: int = 2,
                 seeds_per_job: int = SEEDS_PER_JOB) -> dict:
    """Split each task's `episodes` over `config.jobs_per_task` jobs `(task, first seed, count, config)` (seed blocks
    from `config.task_seed_base(task)`), run `job` over them in `workers` spawned processes (reference_policies
    recorders: each returns (episodes, seeds, dropped)), save each task into `out_dir/file_of(task)` and
    summary.json; returns the summary per task.

    Resumable: each finished job is saved at once into `out_dir/jobs/` with this configuration's fingerprint, and a
    later call with the same configuration runs only the jobs not saved there, so a stop loses at most the jobs
    under way. A job's episodes depend only on its arguments, so the files are the same however often it stopped."""
    out_dir = Path(out_dir)
    parts_dir = out_dir / "jobs"
    parts_dir.mkdir(parents=True, exist_ok=True)
    fingerprint = config_fingerprint(config)
    jobs = []
    for task, total in episodes.items():
        counts = np.full(config.jobs_per_task, total // config.jobs_per_task)
        counts[: total % config.jobs_per_task] += 1
        for j, count in enumerate(counts):
            if count:  # fewer episodes than jobs: the empty jobs are none
                jobs.append((task, config.task_seed_base(task) + j * seeds_per_job, int(count), config))
    def part_of(args) -> Path:  # the file of a job (task, first seed, ...)
        return parts_dir / f"{file_of(args[0])[:-4]}_{args[1]}.npz"

    start = time.perf_counter()
    for args, (recorded, seeds, dropped) in run_saved_jobs(job, jobs, workers, part_of, fingerprint,
                                                           lambda args: args[2]):
        save_part(part_of(args), recorded, seeds, fingerprint, {"dropped": np.array(dropped, np.int64)})
        log.info("%s seeds %d..: %d episodes (%d steps), %d dropped", args[0], args[1], len(recorded),
                 sum(len(e["action"]) for e in recorded), dropped)
    summary = {}
    for task in episodes:
        parts = [load_part(part_of(args)) for args in jobs if args[0] == task]
        recorded = [e for p in parts for e in p[0]]
        seeds = [s for p in parts for s in p[1]]
        lengths = save_episodes(out_dir / file_of(task), recorded, seeds)
        summary[task] = {"episodes": len(recorded), "steps": int(lengths.sum()), "mean_length": float(lengths.mean()),
                         "dropped": int(sum(p[2] for p in parts)), "seed_min": int(min(seeds)), "seed_max": int(max(seeds))}
        log.info("%s: %s", task, summary[task])
    summary["seconds"] = time.perf_counter() - start
    summary["config"] = fingerprint
    atomic_write_json(out_dir / "summary.json", summary, exact=True)
    return summary


def saved_part(path: Path, fingerprint: dict, count: int) -> bool:
    """Whether `path` holds a recording job of `count` episodes made with this configuration `fingerprint` (reads
    only those two small members; a missing, unreadable or foreign file is not one: recorded again)."""
    try:
        with np.load(path) as data:
            return json.loads(str(data["fingerprint"])) == fingerprint and len(data["lengths"]) == count
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return False


def load_part(path: Path, per_episode: tuple[str, ...] = ()) -> tuple[list[dict], list[int], int]:
    """A saved recording job (episodes, seeds, dropped), checked by saved_part; the `per_episode` arrays (one value
    an episode, such as DAgger's `success`) go into each episode as its value."""
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    keys = [k for k in arrays if k not in ("episode", "step", "seeds", "lengths", "dropped", "fingerprint", *per_episode)]
    bounds = np.concatenate([[0], np.cumsum(arrays["lengths"])])
    episodes = [{**{k: arrays[k][a:b] for k in keys}, **{k: arrays[k][i] for k in per_episode}}
                for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:]))]
    return episodes, [int(s) for s in arrays["seeds"]], int(arrays.get("dropped", 0))


def _indexed(args: tuple) -> tuple:
    function, i, job = args
    return i, function(job)


def jobs_as_done(function, jobs: list, workers: int):
    """`function` over `jobs` as `run_jobs` runs them, but yields (index in `jobs`, result) as each job finishes."""
    if workers > 1 and len(jobs) > 1:
        # each worker dies with this process: a stopped recording leaves none recording on (nor their LIBERO servers)
        with multiprocessing.get_context("spawn").Pool(workers, initializer=die_with_parent) as pool:
            yield from pool.imap_unordered(_indexed, [(function, i, job) for i, job in enumerate(jobs)], chunksize=1)
        return
    for i, job in enumerate(jobs):
        yield i, function(job)


def run_jobs(function, jobs: list, workers: int) -> list:
    """`function` over `jobs` as `jobs_as_done` runs them; the results in the jobs' order once all are done."""
    results = [None] * len(jobs)
    for i, result in jobs_as_done(function, jobs, workers):
        results[i] = result
    return results


def run_saved_jobs(function, jobs: list, workers: int, part_of, fingerprint: dict, count_of):
    """Resumable jobs: `function` over the `jobs` whose file `part_of(job)` does not already hold `count_of(job)`
    episodes made with this `fingerprint` (see saved_part); yields (job, result) as each finishes, for the caller to
    `save_part` at once. So a stop loses only the jobs under way, and a slow job never holds back (in memory,
    unsaved) the ones finished after it."""
    pending = [job for job in jobs if not saved_part(part_of(job), fingerprint, count_of(job))]
    if len(pending) < len(jobs):
        log.info("reusing %d of %d jobs saved in %s", len(jobs) - len(pending), len(jobs), part_of(jobs[0]).parent)
    for i, result in jobs_as_done(function, pending, workers):
        yield pending[i], result


def save_part(path: Path, episodes: list[dict], seeds: list[int], fingerprint: dict, extra: dict | None = None) -> None:
    """One finished job's episodes (and `extra` arrays), marked with its configuration `fingerprint`, for saved_part."""
    path.parent.mkdir(parents=True, exist_ok=True)
    save_episodes(path, episodes, seeds, {**(extra or {}), "fingerprint": np.array(json.dumps(fingerprint, sort_keys=True))})


def save_episodes(path: Path, episodes: list[dict], seeds: list[int], extra: dict | None = None) -> np.ndarray:
    """Concatenate per-episode arrays into `path` (the layout of the module docstring, plus `extra` arrays),
    written whole or not at all; returns the (episodes,) int32 lengths."""
    lengths = np.array([len(e["action"]) for e in episodes], np.int32)
    arrays = {key: np.concatenate([e[key] for e in episodes]) for key in episodes[0]}
    arrays["episode"] = np.repeat(np.arange(len(episodes), dtype=np.int32), lengths)
    arrays["step"] = np.concatenate([np.arange(n, dtype=np.int32) for n in lengths])
    arrays["seeds"] = np.array(seeds, np.int64)
    arrays["lengths"] = lengths
    arrays.update(extra or {})
    write_atomic(path, lambda f: np.savez(f, **arrays))  # a temporary of this process's own: workers never share one
    return lengths


# fields added to a recording configuration after recordings were made with it: left out of the fingerprint while
# None (off), so those recordings stay reusable; a value other than None is part of it
ADDED_WHEN_SET = frozenset({"close_below_top", "swaps", "miss"})


def config_fingerprint(config) -> dict:
    """JSON-able description of a recording configuration dataclass (DemoConfig, DaggerConfig), as it reads back
    from summary.json (tuples become lists), to reuse matching recordings."""
    def drop_unset(value):
        if isinstance(value, dict):
            return {k: drop_unset(v) for k, v in value.items() if not (k in ADDED_WHEN_SET and v is None)}
        return value

    return drop_unset(json.loads(json.dumps(asdict(config))))


def finished_recording(out_dir: str | Path, fingerprint: dict, tasks: tuple[str, ...]) -> dict | None:
    """The summary in `out_dir` when a recording with this configuration `fingerprint` finished there (its
    summary.json and every task's file exist), else None."""
    summary = read_json_object(Path(out_dir) / "summary.json")
    if summary is None or not all((Path(out_dir) / f"{t}.npz").is_file() for t in tasks):
        return None
    return summary if summary.get("config") == fingerprint else None


def existing_demos(config: DemoConfig, out_dir: str | Path) -> dict | None:
    """The summary of a finished recording with exactly this configuration in `out_dir`, else None."""
    return finished_recording(out_dir, config_fingerprint(config), config.tasks)


def load_demos(out_dir: str | Path, tasks: tuple[str, ...] = EXPERT_TASKS) -> dict[str, dict[str, np.ndarray]]:
    """{task: arrays} from `record_demos`' files."""
    out = {}
    for task in tasks:
        with np.load(Path(out_dir) / f"{task}.npz") as data:
            out[task] = {k: data[k] for k in data.files}
    return out

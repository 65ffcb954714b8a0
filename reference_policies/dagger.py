"""DAgger corrections: run a reference checkpoint in closed loop and label every state it visits with the expert.

    python -m reference_policies.dagger --model CHECKPOINT --out data/reference_dagger [--episodes 64]

Behaviour cloning learns the expert's states only; a policy that drifts (a can carried past its bin, to the
arm's reach limit) meets states no demonstration shows and keeps drifting. Here the checkpoint acts exactly
as the evaluation runs it (its harness.toml conventions, temporal ensembling, fast render), and at every step
the state-based expert (`CanLabeller`) says what it would do there. Those labels, on the policy's own
inputs, are added to the demonstrations for a fine-tuning stage (`pipeline --dagger-episodes N`).

Seeds: episode k uses DAGGER_SEED_BASE + k, apart from the demonstration seeds (100000..) and the
evaluation seeds 0..49. Episodes run in spawned processes (never fork after rendering), in a fixed split
of jobs, so the data do not depend on the number of workers. An episode stops at success or `max_steps`.

Output: `<out>/<task>.npz` with the arrays of `reference_policies.demos` (the policy's resized inputs,
proprio, the expert's label as `action`, episode, step, seeds, lengths) plus `success` (episodes,) bool,
and `<out>/summary.json` (counts, policy success, seconds, configuration and checkpoint fingerprint).
Resumable: each finished job is saved at once into `<out>/jobs/`, and a later call with the same configuration and
checkpoint runs only the jobs not saved there.
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from harness.files import atomic_write_json
from harness.options import option
from reference_policies.demos import (config_fingerprint, finished_recording, load_part, run_saved_jobs, save_episodes,
                                     save_part)
from reference_policies.experts import CanLabeller, ExpertConfig
from reference_policies.options import Workers, add_options, parse, values

log = logging.getLogger(__name__)

DAGGER_SEED_BASE = 400_000
LABELLERS = {CanLabeller.task: CanLabeller}  # task -> its state-based expert


@dataclass(frozen=True)
class DaggerConfig:
    task: str = option("PickPlaceCan", "--task", "the task whose state-based expert labels the states",
                       choices=tuple(LABELLERS))
    episodes: int = option(64, "--episodes", "episodes of the checkpoint, each state labelled", type=int)
    # the demonstrations' limit for PickPlaceCan
    max_steps: int = option(300, "--max-steps", "step limit of an episode", type=int)
    jobs: int = 4  # fixed split (not the worker count), so the data do not depend on the workers
    expert: ExpertConfig = ExpertConfig()  # the labeller's waypoints (the demonstrations' expert's); fingerprinted

    def __post_init__(self) -> None:
        if self.task not in LABELLERS:
            raise ValueError(f"no state-based expert for {self.task!r}; DAgger labels {', '.join(LABELLERS)}")
        if self.episodes < self.jobs or self.max_steps < 1:
            raise ValueError(f"--episodes must be >= {self.jobs} (one per job) and --max-steps >= 1")


def checkpoint_fingerprint(model_dir: str | Path) -> str:
    """sha256 over a checkpoint folder's config, statistics, conventions (harness.toml, when there) and parameter
    files (which policy collected the data)."""
    digest = hashlib.sha256()
    root = Path(model_dir)
    files = [root / "config.json", root / "dataset_statistics.json", *sorted(root.glob("harness.toml")),
             *sorted(root.glob("*/default/checkpoint"))]
    for path in files:
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def policy_in_env(model_dir: str | Path, task: str, max_steps: int, model=None):
    """(env, policy): `task` made as the evaluation runs the checkpoint (its harness.toml conventions, fast render,
    no masks) and the checkpoint's policy, checked against it; `model`: the checkpoint's loaded policy
    (`load_policy`), when it is loaded already."""
    import envs
    from harness.conventions import CheckpointConventions

    conventions = CheckpointConventions.read(model_dir)
    options = conventions.env_options({"fast_render": True, "masks": False})
    env = envs.make(task, options, max_episode_steps=max_steps)
    model = model if model is not None else _load_model(model_dir, conventions)
    policy = model.closed_loop(conventions.policy_config())
    policy.check_env(env)
    return env, policy


def _load_model(model_dir: str | Path, conventions=None):
    from harness.conventions import CheckpointConventions
    from harness.policies import load_policy

    conventions = conventions or CheckpointConventions.read(model_dir)
    return load_policy(str(model_dir), text_tokenizer=conventions.text_tokenizer)


# The (env, policy) of the collection under way in this process, for its next job: loading the checkpoint (and its
# compiled programs) and starting the simulator (for LIBERO a server process) once per process and task instead of
# once per job. Only within one collection (`collect` ends it; a pool's worker process ends with its pool), so a
# checkpoint rewritten between collections is loaded again. Per thread: an env is only stepped (and closed) from the
# thread that made it, and collections in two threads keep theirs apart.
# Every episode starts from `env.reset(seed=...)` and `policy.reset(..., seed=...)`, as the episodes of one job did
# already, so a job's data are those of a fresh env and policy (the resume tests compare the two).
_local = threading.local()


def _reused() -> dict:
    if not hasattr(_local, "reused"):
        _local.reused = {}
    return _local.reused


def reused_policy_in_env(model_dir: str | Path, task: str, max_steps: int):
    """policy_in_env's (env, policy), the one made for the same arguments by this thread's previous job of the
    collection under way when there is one (the previous one closed when the arguments differ)."""
    reused = _reused()
    key = (str(model_dir), task, max_steps)
    if reused.get("key") != key:
        model = reused.get("model") if reused.get("model_dir") == str(model_dir) else None  # another task's
        _close_env()
        model = model if model is not None else _load_model(model_dir)
        reused.update(key=key, made=policy_in_env(model_dir, task, max_steps, model), model=model,
                      model_dir=str(model_dir))
    return reused["made"]


def _close_env() -> None:
    made = _reused().pop("made", None)
    _reused().pop("key", None)
    if made is not None:
        made[0].close()


def end_reuse() -> None:
    """Close the env kept for the next job (reused_policy_in_env) and drop the loaded checkpoint: the collection is
    over, or its env was left mid-episode."""
    _close_env()
    _reused().clear()


def labelled_episode(env, policy, label, obs: dict, info: dict, seed: int, max_steps: int) -> dict:
    """One closed-loop episode from a fresh reset (`obs`, `info`): the policy acts, `label(obs)` says what the expert
    would do at each visited state -> {the policy's inputs..., "action": labels, "seed", "success"}; stops at
    success or after `max_steps`."""
    policy.reset(info.get("instruction", ""), seed=seed)
    steps: dict[str, list] = {}
    success = False
    for _ in range(max_steps):
        decision = policy.step(obs)
        for key, value in {**decision.inputs, "action": label(obs)}.items():
            steps.setdefault(key, []).append(value)
        obs, _, terminated, truncated, info = env.step(decision.action)
        success = bool(info["success"])
        if success or terminated or truncated:
            break
    # inputs as the policy was fed them (proprio float32), labels float32 from the expert's control law
    return {**{k: np.stack(v) for k, v in steps.items()}, "seed": seed, "success": success}


def save_collection(out_dir: Path, episodes: list[dict], file_name: str) -> dict:
    """Write a task's labelled episodes (sorted by seed) into `out_dir/file_name` with their `success` flags ->
    {episodes, steps, policy_successes, mean_length}."""
    episodes = sorted(episodes, key=lambda e: e["seed"])
    success = np.array([e.pop("success") for e in episodes], bool)
    seeds = [e.pop("seed") for e in episodes]
    lengths = save_episodes(out_dir / file_name, episodes, seeds, {"success": success})
    return {"episodes": len(episodes), "steps": int(lengths.sum()), "policy_successes": int(success.sum()),
            "mean_length": float(lengths.mean())}


def save_labelled_part(path: Path, episodes: list[dict], fingerprint: dict) -> np.ndarray:
    """One finished collection job's episodes ({arrays..., "seed", "success"}) saved with their `success` flags and
    the collection's `fingerprint`; returns the flags."""
    success = np.array([e.pop("success") for e in episodes], bool)
    seeds = [e.pop("seed") for e in episodes]
    save_part(path, episodes, seeds, fingerprint, {"success": success})
    return success


def load_labelled_parts(paths) -> list[dict]:
    """The episodes saved by save_labelled_part in `paths`, in order, each with its "seed" and "success" again."""
    episodes = []
    for path in paths:
        saved, seeds, _ = load_part(path, per_episode=("success",))
        episodes += [{**e, "seed": seed} for e, seed in zip(saved, seeds)]
    return episodes


def _collect_job(args: tuple) -> list[dict]:
    """Spawned worker: the episodes of seeds `seeds`, each {arrays..., "seed", "success"}."""
    model_dir, config, seeds = args
    env, policy = reused_policy_in_env(model_dir, config.task, config.max_steps)  # the same for the next job
    labeller = LABELLERS[config.task](config.expert)
    episodes = []
    try:
        for seed in seeds:
            obs, info = env.reset(seed=seed)
            labeller.reset(obs, env)
            episodes.append(labelled_episode(env, policy, lambda o: labeller.act(o, env), obs, info, seed,
                                             config.max_steps))
    except BaseException:
        end_reuse()  # an env left mid-episode by an error is not reused
        raise
    return episodes


def collect(model_dir: str | Path, out_dir: str | Path, config: DaggerConfig = DaggerConfig(), workers: int = 2) -> dict:
    """Run the checkpoint on `config.episodes` seeds, label every visited state; write `<out>/<task>.npz`."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    seeds = [DAGGER_SEED_BASE + k for k in range(config.episodes)]
    jobs = [(str(model_dir), config, seeds[j::config.jobs]) for j in range(config.jobs)]
    start = time.perf_counter()
    fp = fingerprint(config, model_dir)

    def part_of(job) -> Path:  # each finished job is saved at once, so a stop loses only the jobs under way
        return out_dir / "jobs" / f"{config.task}_{job[2][0]}.npz"

    try:
        for job, episodes in run_saved_jobs(_collect_job, jobs, workers, part_of, fp, lambda job: len(job[2])):
            success = save_labelled_part(part_of(job), episodes, fp)
            log.info("%s seeds %d..: %d episodes collected, %d successes", config.task, job[2][0], len(success),
                     success.sum())
    finally:
        end_reuse()  # the env of the jobs run in this process (one worker)
    episodes = load_labelled_parts(part_of(job) for job in jobs)
    summary = {config.task: save_collection(out_dir, episodes, f"{config.task}.npz"),
               "seconds": time.perf_counter() - start, "config": fp}
    atomic_write_json(out_dir / "summary.json", summary, exact=True)
    log.info("%s: %s", config.task, summary[config.task])
    return summary


def fingerprint(config: DaggerConfig, model_dir: str | Path) -> dict:
    """JSON-able description of a collection: its configuration and the checkpoint that acted."""
    return {**config_fingerprint(config), "checkpoint": checkpoint_fingerprint(model_dir)}


def existing(config: DaggerConfig, model_dir: str | Path, out_dir: str | Path) -> dict | None:
    """The summary of a finished collection with this configuration and checkpoint in `out_dir`, else None."""
    return finished_recording(out_dir, fingerprint(config, model_dir), (config.task,))


def append_corrections(demos: dict[str, dict[str, np.ndarray]], out_dir: str | Path, task: str,
                       file_name: str | None = None) -> dict[str, dict[str, np.ndarray]]:
    """`demos` with the corrections of `task` in `out_dir/file_name` (default `<task>.npz`) appended as further
    episodes of that task."""
    file_name = file_name or f"{task}.npz"
    with np.load(Path(out_dir) / file_name) as data:
        extra = {k: data[k] for k in data.files}
    return append_episodes(demos, task, extra, f"{out_dir}/{file_name}")


def append_episodes(demos: dict[str, dict[str, np.ndarray]], task: str, extra: dict[str, np.ndarray],
                    source: str) -> dict[str, dict[str, np.ndarray]]:
    """`demos` with the episodes `extra` (the recording layout, episodes numbered from 0) appended to `task`'s;
    `source` names where they came from when one of `task`'s arrays is missing."""
    base = demos[task]
    first = int(base["episode"].max()) + 1
    merged = {}
    if "weight" in extra and "weight" not in base:  # weighted corrections: the demonstrations weigh 1
        base = {**base, "weight": np.ones(len(base["action"]), np.float64)}
    for key, value in base.items():
        if key == "weight" and key not in extra:
            merged[key] = np.concatenate([value, np.ones(len(extra["action"]), value.dtype)])
        elif key == "episode":
            merged[key] = np.concatenate([value, extra[key] + first])
        elif key in extra:
            merged[key] = np.concatenate([value, extra[key].astype(value.dtype)])
        else:
            raise ValueError(f"{source} lacks {key!r}; record it again")
    return {**demos, task: merged}


@dataclass(frozen=True)
class DaggerOptions:
    """The command's own options; what it collects is `DaggerConfig`'s fields, the processes `Workers`'."""
    model: str = option(flag="--model", help="checkpoint folder that acts")
    out: str = option(flag="--out", help="folder for the labelled states (not committed)")

    def __post_init__(self) -> None:
        if not (Path(self.model) / "config.json").is_file():
            raise ValueError(f"{self.model} is not a checkpoint folder (no config.json); pass --model a saved "
                             "reference policy")


def command_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m reference_policies.dagger", description=__doc__.splitlines()[0])
    add_options(parser, (DaggerOptions, DaggerConfig, Workers))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = command_parser()
    args, options = parse(parser, DaggerOptions, argv)
    try:
        config = DaggerConfig(**values(DaggerConfig, args))
        workers = Workers(**values(Workers, args)).workers
    except ValueError as e:
        parser.error(str(e))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    collect(options.model, options.out, config, workers=workers)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

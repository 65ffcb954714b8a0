"""Evaluation runs: many episodes over tasks; a straight pipeline make env -> policy -> rollout -> writers -> results.

`run(config)` returns a `RunSummary` and writes `results/runs/<run>/<task>/episode_<k>/...` plus
`results/runs/<run>/results.json` (manifest + one row per episode). A failing episode is recorded
as failed (with its error) and the run goes on; Ctrl-C aborts the current episode's writer (no
half-written files) and re-raises.
"""

from __future__ import annotations

import logging
import platform
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

import envs
from harness.files import atomic_write_json
from harness.octo import load_pretrained
from harness.policy import OctoPolicy, PolicyConfig, resize_frame
from harness.records import EpisodeMeta, StepRecord
from harness.rollout import rollout
from harness.writers import EpisodeWriter, OutputOptions

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunConfig:
    tasks: tuple[str, ...]
    model: str
    episodes: int = 1
    seed: int = 0  # episode k of every task uses seed + k
    max_steps: int | None = None  # None = the task's own limit
    out_dir: Path = Path("results/runs")
    run_name: str | None = None  # default: <UTC time>_<model short name>
    instruction: str | None = None  # override the task's default instruction
    masks: bool = True  # ask the env for target/robot masks (attention mass on the target)
    fast_render: bool = False  # no reflections/shadows/anti-aliasing: ~3.6x faster frames, near-identical pixels
    goal_images: Path | None = None  # folder with <obs key>.png goal images (goal-conditioned models)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    outputs: OutputOptions = field(default_factory=OutputOptions)


@dataclass(frozen=True)
class EpisodeRow:
    task: str
    episode: int
    seed: int
    status: str  # "ok" | "failed"
    success: bool
    steps: int
    seconds_per_step: float | None  # None for failed episodes
    simulation_per_step: float | None
    inference_per_step: float | None
    overhead_fraction: float | None  # (step - simulation - inference) / step
    directory: str
    error: str | None = None


@dataclass(frozen=True)
class RunSummary:
    run_dir: Path
    rows: tuple[EpisodeRow, ...]
    manifest: dict

    def table(self) -> str:
        """Per-task summary table (plain text)."""
        header = f"{'task':<20} {'episodes':>8} {'failed':>6} {'success':>8} {'steps':>6} {'s/step':>7} {'sim':>6} {'infer':>6} {'overhead':>8}"
        lines = [header, "-" * len(header)]
        for task in dict.fromkeys(r.task for r in self.rows):
            rows = [r for r in self.rows if r.task == task]
            ok = [r for r in rows if r.status == "ok"]
            mean = (lambda xs: float(np.mean(xs)) if xs else float("nan"))
            lines.append(
                f"{task:<20} {len(rows):>8} {len(rows) - len(ok):>6} "
                f"{sum(r.success for r in ok)}/{len(rows):<6} {mean([r.steps for r in ok]):>6.1f} "
                f"{mean([r.seconds_per_step for r in ok]):>7.3f} {mean([r.simulation_per_step for r in ok]):>6.3f} "
                f"{mean([r.inference_per_step for r in ok]):>6.3f} {mean([r.overhead_fraction for r in ok]):>8.1%}"
            )
        return "\n".join(lines)


def _git_commit() -> str | None:
    """Commit of the harness checkout, read from .git without starting a process (no fork next to JAX threads)."""
    git = Path(__file__).resolve().parents[1] / ".git"
    try:
        head = (git / "HEAD").read_text().strip()
        if not head.startswith("ref: "):
            return head
        ref = head[5:]
        if (git / ref).exists():
            return (git / ref).read_text().strip()
        for line in (git / "packed-refs").read_text().splitlines():
            if line.endswith(" " + ref):
                return line.split()[0]
    except OSError:
        pass
    return None


def _manifest(config: RunConfig, model, policy: OctoPolicy) -> dict:
    import jax
    import robosuite

    tokenizer = getattr(model, "text_tokenizer", None)
    return {
        "model": model.source,
        "model_is_random": bool(model.is_random),
        "model_note": "RANDOM WEIGHTS - actions and attention are not Octo's" if model.is_random else "",
        "text_tokenizer": _tokenizer_label(tokenizer),
        "dataset_key": policy.dataset_key,
        "execution": config.policy.describe(),
        "tasks": list(config.tasks),
        "episodes": config.episodes,
        "seed": config.seed,
        "max_steps": config.max_steps,
        "outputs": asdict(config.outputs),
        "git_commit": _git_commit(),
        "versions": {"jax": jax.__version__, "robosuite": robosuite.__version__, "python": platform.python_version()},
    }


def _tokenizer_label(tokenizer) -> str:
    if tokenizer is None:
        return "none (goal-conditioned model)"
    if getattr(tokenizer, "is_fallback", False):
        return f"{tokenizer.name} [fallback tokenizer]"
    return tokenizer.name


def run(
    config: RunConfig,
    *,
    model=None,
    on_step: Callable[[str, int, int, StepRecord], None] | None = None,
) -> RunSummary:
    """Run every episode of every task. `model` may be passed in to reuse an already loaded one."""
    for task in config.tasks:
        envs.get_task(task)  # unknown task -> clear error before anything is loaded or written
    if model is None:
        model = load_pretrained(config.model)
    if model.is_random:
        log.warning("model %s has RANDOM weights: actions and attention are not Octo's", model.source)
    policy = OctoPolicy(model, config.policy)
    goals = load_goal_images(config.goal_images, model.goal_image_sizes) if config.goal_images else None
    if goals is None and model.config.language is None:
        raise ValueError(f"{model.source} is goal-conditioned (no language input); pass --goal-images DIR holding "
                         f"{', '.join(k + '.png' for k in sorted(model.goal_image_sizes))}")
    run_name = config.run_name or f"{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}_{_short(model.source)}"
    run_dir = Path(config.out_dir) / run_name
    manifest = _manifest(config, model, policy)
    rows: list[EpisodeRow] = []
    tokens = model.token_map()
    for task in config.tasks:
        env = envs.make(task, masks=config.masks, instruction=config.instruction, fast_render=config.fast_render)
        try:
            for k in range(config.episodes):
                rows.append(_run_episode(config, env, policy, goals, tokens, task, k, run_dir, manifest, on_step))
                atomic_write_json(run_dir / "results.json", {"manifest": manifest, "episodes": [asdict(r) for r in rows]})
        finally:
            env.close()
    return RunSummary(run_dir=run_dir, rows=tuple(rows), manifest=manifest)


def _short(source: str) -> str:
    return source.rstrip("/").replace("hf://", "").replace("random:", "random-").split("/")[-1].replace(":", "-")


def load_goal_images(folder: Path, sizes: dict[str, tuple[int, int]]) -> dict[str, np.ndarray]:
    """<folder>/<obs key>.png for each goal key the model takes -> {key: (height, width, 3) uint8} at its size."""
    goals = {}
    for key, size in sizes.items():
        path = Path(folder) / f"{key}.png"
        if path.is_file():
            goals[key] = resize_frame(np.asarray(Image.open(path).convert("RGB")), size)
    if not goals:
        raise FileNotFoundError(f"no goal images in {folder}; expected {', '.join(k + '.png' for k in sorted(sizes))}")
    return goals


def _run_episode(config, env, policy, goals, tokens, task, k, run_dir, manifest, on_step) -> EpisodeRow:
    seed = config.seed + k
    episode_dir = run_dir / task / f"episode_{k}"
    instruction = config.instruction or envs.get_task(task).instruction
    meta = EpisodeMeta(
        run=run_dir.name,
        task=task,
        episode=k,
        seed=seed,
        instruction=instruction,
        model=manifest["model"],
        model_is_random=manifest["model_is_random"],
        dataset_key=manifest["dataset_key"],
        text_tokenizer=manifest["text_tokenizer"],
        execution=manifest["execution"],
    )
    writer = None
    step_cb = (lambda t, rec: on_step(task, k, t, rec)) if on_step else None
    try:
        writer = EpisodeWriter(episode_dir, tokens, meta, config.outputs)
        result = rollout(env, policy, writer.add_step, seed=seed, instruction=instruction, goals=goals,
                         max_steps=config.max_steps, on_step=step_cb)
        writer.finish(
            {
                "success": result.success,
                "steps": result.steps,
                "total_reward": result.total_reward,
                "actions_clipped": result.actions_clipped,
                "timings": result.timings,
            }
        )
    except KeyboardInterrupt:
        if writer is not None:
            writer.abort()
        raise
    except Exception as exc:  # a failing episode is recorded and the run goes on
        if writer is not None:
            writer.abort()
        error = f"{type(exc).__name__}: {exc}"
        log.error("episode %s/%d failed: %s", task, k, error)
        try:
            atomic_write_json(episode_dir / "episode.json", {**asdict(meta), "status": "failed", "success": False,
                                                             "error": error, "traceback": traceback.format_exc()})
        except OSError as write_error:  # the episode folder itself may be what failed; results.json still has it
            log.error("could not write %s: %s", episode_dir / "episode.json", write_error)
        return EpisodeRow(task, k, seed, "failed", False, 0, None, None, None, None, str(episode_dir), error)
    n = max(result.steps, 1)
    step = result.timings["step"] / n
    sim = result.timings["simulation"] / n
    inf = result.timings["inference"] / n
    return EpisodeRow(task, k, seed, "ok", result.success, result.steps, step, sim, inf,
                      (step - sim - inf) / step if step > 0 else 0.0, str(episode_dir))


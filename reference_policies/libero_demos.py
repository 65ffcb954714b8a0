"""LIBERO-Object demonstrations from the scripted expert, recorded through the harness's LIBERO env path.

Each episode starts from a placement LIBERO's own sampler draws (`LiberoEnv.reset(seed=s, options={"initial_state":
"sampled"})`: the BDDL regions the suite's stored states were drawn from) with seeds LIBERO_SEED_BASE + 10_000 *
task + k, never from the 50 stored initial states the published evaluation uses. The demonstrator is the timed
LIBERO-Object expert (`LiberoObjectExpert`, whose close phase lasts 12 steps that no single frame tells apart: the
committed policy, trained on it, stays closed at the grasp) or, with `demonstrator="state"`, the state-based one
(`LiberoObjectLabeller`: its phase is read off the state, so it lifts as soon as the fingers hold the object and
every frame shows what comes next). The env is the one the policy will be evaluated in: cameras at the model's sizes (agentview 128 px, eye-in-hand 64 px, so no resize), the "rot180"
image convention of OpenVLA's LIBERO datasets, fast render, the "libero" action space (6 OSC values in [-1, 1],
gripper 1 open / 0 closed), LIBERO's 8-D proprio. As for the robosuite reference (reference_policies.demos), Gaussian
noise perturbs the *executed* arm input while the label stays the expert's clean action (DART), so the data cover
the states a learned policy drifts into; an episode the expert fails under noise is dropped and the next seed used.

Output per task: `<suite>_<index>.npz` in the layout of reference_policies.demos (image_primary, image_wrist,
proprio, action, episode, step, seeds, lengths), plus summary.json.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reference_policies.demos import (config_fingerprint, finished_recording, noisy_episode, record_tasks,
                                     successful_episodes)
from reference_policies.libero_expert import LiberoExpertConfig, LiberoObjectExpert, LiberoObjectLabeller


DEMONSTRATORS = {"state": LiberoObjectLabeller, "timed": LiberoObjectExpert}  # both: act(env, obs)
LIBERO_SEED_BASE = 1_000_000  # placement seeds of task i: 1_000_000 + 10_000 i + k (evaluation uses stored states)
SEEDS_PER_JOB = 1_000
SWAP_SEED_OFFSET = 5_000  # swapped-instruction demonstrations' seeds: after the own ones' 5 jobs x 1000 seeds
LIBERO_OBJECT_TASKS = tuple(f"libero_object/{i}" for i in range(10))
# the reference model's cameras: observation key -> (LIBERO camera, square size rendered)
# (the wrist at 128 px = 8x8 patches, as the robosuite reference reads it; the first LIBERO policy read 64 px = 4x4)
LIBERO_CAMERAS = (("image_primary", "agentview", 128), ("image_wrist", "robot0_eye_in_hand", 128))


@dataclass(frozen=True)
class MissConfig:
    """Missed grasps: with probability `rate` an episode's hand is driven, until it has closed for `close_steps`
    steps, by the state-based expert aiming at a grasp point `offset` (m) beside the named object's, in a random
    horizontal direction: it descends beside the object and closes there (on nothing, or on the object's edge).
    Then the real expert takes over from there (open, rise, re-centre, grasp again). These are the states where the
    reference policy stalls (docs/libero-reference.md: open, about 3 cm off the object's centre, at its height).
    As with the bursts, what is executed is perturbed and the label stays the real expert's, so the recording never
    teaches the offset, only the way back."""
    rate: float = 0.5
    offset: float = 0.03
    close_steps: tuple[int, int] = (6, 10)  # inclusive range

    def __post_init__(self) -> None:
        if not 0.0 <= self.rate <= 1.0:
            raise ValueError(f"a missed grasp's rate is a probability in [0, 1], not {self.rate}")


class MissedGrasp:
    """`perturb(executed, label, rng) -> executed` (see MissConfig), for one episode in `env`; `see(obs)` must be
    given each step's observation before the perturbation (record_episode does)."""

    def __init__(self, config: MissConfig, env, target: str, expert, rng: np.random.Generator):
        from reference_policies.libero_expert import LiberoObjectLabeller

        self.env, self.target = env, target
        self.labeller = LiberoObjectLabeller(target, config=expert)
        self.active = bool(rng.random() < config.rate)
        angle = rng.uniform(0.0, 2 * np.pi)
        self.offset = config.offset * np.array([np.cos(angle), np.sin(angle), 0.0])
        self.close_steps = int(rng.integers(config.close_steps[0], config.close_steps[1] + 1))
        self.closed = 0
        self.obs: dict | None = None
        self.closes: list[tuple[float, float]] = []  # per close step: the hand from the object's centre, above its top (m)

    def see(self, obs: dict) -> dict:
        self.obs = obs
        return obs

    def __call__(self, executed: np.ndarray, label: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        from reference_policies.libero_expert import CLOSED

        if not self.active or self.env.grasping(self.target):  # held after all: the miss is over
            self.active = False
            return executed
        poses = dict(self.env.object_poses())
        box = poses[self.target]
        poses[self.target] = {**box, "low": box["low"] + self.offset, "high": box["high"] + self.offset}
        action = self.labeller.act_on(self.obs, poses, held=False)
        if action[6] == CLOSED:
            hand = np.asarray(self.obs["proprio"][:3], np.float64)
            self.closed += 1
            self.active = self.closed < self.close_steps
            self.closes.append((float(np.linalg.norm(hand[:2] - (box["low"][:2] + box["high"][:2]) / 2)),
                                float(hand[2] - box["high"][2])))
        return action


@dataclass(frozen=True)
class BurstConfig:
    """Recovery bursts (DART-style, beyond the Gaussian noise): stretches of steps whose *executed* input is not the
    expert's, so that the recording holds the states a learned policy drifts into and the expert's way back out.
    Per step, when no burst runs: with probability `push` a push starts (`push_steps` steps of a constant horizontal
    input of size `push_size` in a random direction: an off-centre approach, a nudged object), and with probability
    `gripper` a premature close starts (`gripper_steps` steps with the gripper closed while the expert holds it open:
    a grasp closed on nothing or beside the object). Labels stay the expert's, who reads the state and recovers."""
    push: float = 0.02
    push_steps: tuple[int, int] = (3, 7)  # inclusive range
    push_size: float = 0.6
    gripper: float = 0.015
    gripper_steps: tuple[int, int] = (4, 10)
    miss: MissConfig | None = None  # None: no missed grasps (left out of fingerprints while None)


class Bursts:
    """`perturb(executed, label, rng) -> executed` for reference_policies.demos.noisy_episode (see BurstConfig)."""

    def __init__(self, config: BurstConfig):
        self.config = config
        self.left = 0  # steps left in the running burst
        self.kind = ""
        self.direction = np.zeros(2)

    def __call__(self, executed: np.ndarray, label: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        from reference_policies.libero_expert import CLOSED, OPEN

        c = self.config
        if self.left == 0:
            draw = rng.random()
            if draw < c.push:
                self.kind, self.left = "push", int(rng.integers(c.push_steps[0], c.push_steps[1] + 1))
                angle = rng.uniform(0.0, 2 * np.pi)
                self.direction = c.push_size * np.array([np.cos(angle), np.sin(angle)])
            elif draw < c.push + c.gripper and label[6] == OPEN:
                self.kind, self.left = "gripper", int(rng.integers(c.gripper_steps[0], c.gripper_steps[1] + 1))
        if self.left == 0:
            return executed
        self.left -= 1
        executed = executed.copy()
        if self.kind == "push":
            executed[:2] = self.direction
        else:
            executed[6] = CLOSED
        return executed


@dataclass(frozen=True)
class LiberoDemoConfig:
    tasks: tuple[str, ...] = LIBERO_OBJECT_TASKS
    episodes: int = 50  # demonstrations per task (LIBERO's own count)
    jobs_per_task: int = 5  # fixed split, so the data do not depend on the number of workers; each job saved alone
    cameras: tuple[tuple[str, str, int], ...] = LIBERO_CAMERAS
    image_convention: str = "rot180"
    fast_render: bool = True
    noise: float = 0.3  # std of the Gaussian noise on the executed position input (OSC units)
    max_steps: int = 280  # LIBERO-Object's step limit
    expert: LiberoExpertConfig = field(default_factory=LiberoExpertConfig)
    # "timed": LiberoObjectExpert, whose close phase is a 12-step timer no single frame shows (the committed policy's);
    # "state": LiberoObjectLabeller, whose phase is read off the state (it lifts once the fingers hold the object)
    demonstrator: str = "state"
    bursts: BurstConfig | None = field(default_factory=BurstConfig)  # None: Gaussian noise only (the first policy)
    # True: swapped-instruction demonstrations: in each task's scene the expert picks *another* task's named object
    # that the scene also holds (swap_candidates, one per seed in turn), and the episode is kept when that object,
    # alone, ends in the basket; its instruction is that task's (append_swaps). Seeds from the task's block + 5000,
    # never the own demonstrations'. None: the task's own object (left out of fingerprints while None)
    swaps: bool | None = None

    def __post_init__(self) -> None:
        if self.demonstrator not in DEMONSTRATORS:
            raise ValueError(f"demonstrator {self.demonstrator!r}: use one of {', '.join(DEMONSTRATORS)}")

    def task_seed_base(self, task: str) -> int:
        return LIBERO_SEED_BASE + 10_000 * int(task.split("/")[1]) + (SWAP_SEED_OFFSET if self.swaps else 0)


def task_file(task: str) -> str:
    """"libero_object/3" -> "libero_object_3.npz"."""
    return task.replace("/", "_") + ".npz"


def make_env(task: str, config: LiberoDemoConfig):
    import envs

    return envs.make(task, cameras={k: (c, s) for k, c, s in config.cameras}, image_convention=config.image_convention,
                     fast_render=config.fast_render, action_space="libero", max_episode_steps=config.max_steps)


def swap_candidates(task: str, movable, tasks: tuple[str, ...] = LIBERO_OBJECT_TASKS) -> list[str]:
    """The other tasks whose named object scene `task` also holds (`movable`: its movable objects), in the order
    i+1, i+2, ... (mod the number of tasks): the instructions a swap may give in that scene."""
    from envs.libero_tasks import get_libero_task

    i = tasks.index(task)
    others = (tasks[(i + step) % len(tasks)] for step in range(1, len(tasks)))
    return [t for t in others if get_libero_task(t).targets[0] in set(movable)]


def evaluation_swap(task: str, movable, tasks: tuple[str, ...] = LIBERO_OBJECT_TASKS) -> str | None:
    """The task whose instruction the evaluation's swap tells scene `task`: swap_candidates' first, or None."""
    candidates = swap_candidates(task, movable, tasks)
    return candidates[0] if candidates else None


def placed_alone(env, target: str) -> bool:
    """Whether `target`, and no other object, is in the task's goal (the basket), released (not held)."""
    outcome = env.episode_outcome()
    return outcome["placed"] == [target] and target not in outcome["held"]


def record_episode(env, target: str, seed: int, config: LiberoDemoConfig, succeeded=None) -> dict | None:
    """One noisy expert episode from sampled placement `seed`; arrays as in reference_policies.demos, or None when
    the expert failed (`succeeded(info)` says when it succeeded; default: the task's own predicate)."""
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed, options={"initial_state": "sampled"})
    expert = DEMONSTRATORS[config.demonstrator](target, config=config.expert)
    sizes = {k: s for k, _, s in config.cameras}  # rendered at the model's sizes: stored as rendered
    perturb = Bursts(config.bursts) if config.bursts is not None else None
    act = lambda o: expert.act(env, o)  # noqa: E731
    if config.bursts is not None and config.bursts.miss is not None:  # (draws nothing from rng while unset)
        miss, bursts = MissedGrasp(config.bursts.miss, env, target, config.expert, rng), perturb
        act = lambda o: expert.act(env, miss.see(o))  # noqa: E731

        def perturb(executed, label, r):  # the miss while it runs, then the bursts
            return miss(executed, label, r) if miss.active else bursts(executed, label, r)
    return noisy_episode(env, obs, act, sizes, config.noise, rng, config.max_steps, perturb, succeeded)


def _record_job(args: tuple) -> tuple[list[dict], list[int], int]:
    """Spawned worker: `count` successful episodes of `task` from placement seeds `first_seed`, `first_seed + 1`...
    (with `config.swaps`, each naming swap_candidates' object number seed mod their count, its task's index in
    LIBERO_OBJECT_TASKS stored per frame as "named")."""
    task, first_seed, count, config = args
    from envs.libero_tasks import get_libero_task

    env = make_env(task, config)
    try:
        if not config.swaps:
            target = get_libero_task(task).targets[0]
            return successful_episodes(lambda seed: record_episode(env, target, seed, config), task, first_seed,
                                       count, SEEDS_PER_JOB)
        candidates = swap_candidates(task, env.description.get("movable", env.description["objects"]))
        if not candidates:
            raise RuntimeError(f"{task}: its scene holds no other task's named object; leave it out of swaps")

        def swapped(seed: int) -> dict | None:
            named = candidates[seed % len(candidates)]
            target = get_libero_task(named).targets[0]
            episode = record_episode(env, target, seed, config, lambda info: placed_alone(env, target))
            if episode is not None:
                episode["named"] = np.full(len(episode["action"]), LIBERO_OBJECT_TASKS.index(named), np.int32)
            return episode

        return successful_episodes(swapped, task, first_seed, count, SEEDS_PER_JOB)
    finally:
        env.close()


def record_libero_demos(config: LiberoDemoConfig, out_dir: str | Path, workers: int = 2) -> dict:
    """Record every task's demonstrations into `out_dir/<suite>_<index>.npz`; returns a summary per task."""
    return record_tasks(_record_job, config, {t: config.episodes for t in config.tasks}, out_dir, task_file, workers,
                        SEEDS_PER_JOB)


def existing_libero_demos(config: LiberoDemoConfig, out_dir: str | Path) -> dict | None:
    """The summary of a finished recording with exactly this configuration in `out_dir`, else None."""
    return finished_recording(out_dir, config_fingerprint(config), tuple(task_file(t)[:-4] for t in config.tasks))


def append_swaps(demos: dict[str, dict[str, np.ndarray]], swap_dir: str | Path,
                 tasks: tuple[str, ...]) -> dict[str, dict[str, np.ndarray]]:
    """`demos` with the swapped-instruction demonstrations in `swap_dir` (one file a scene task, from
    `record_libero_demos` with `swaps=True`) appended to the task each one *named*: its instruction is that task's.
    A demonstration naming a task outside `demos` is a ValueError (record the swaps with the same tasks)."""
    from reference_policies.dagger import append_episodes

    for scene in tasks:
        with np.load(Path(swap_dir) / task_file(scene)) as data:
            arrays = {k: data[k] for k in data.files}
        named_of_episode = arrays["named"][np.r_[0, np.cumsum(arrays["lengths"])[:-1]]]
        for index in np.unique(named_of_episode):
            keep = named_of_episode == index
            frames = keep[arrays["episode"]]
            extra = {k: v[frames] for k, v in arrays.items() if k not in ("named", "seeds", "lengths") and len(v) == len(frames)}
            extra["episode"] = np.repeat(np.arange(int(keep.sum()), dtype=np.int32), arrays["lengths"][keep])
            extra.update(seeds=arrays["seeds"][keep], lengths=arrays["lengths"][keep])
            named = LIBERO_OBJECT_TASKS[int(index)] if 0 <= index < len(LIBERO_OBJECT_TASKS) else f"task number {index}"
            if named not in demos:
                raise ValueError(f"{swap_dir}/{task_file(scene)} names {named}, which has no demonstrations here")
            demos = append_episodes(demos, named, extra, f"{swap_dir}/{task_file(scene)}")
    return demos


def load_libero_demos(out_dir: str | Path, tasks: tuple[str, ...]) -> dict[str, dict[str, np.ndarray]]:
    """{task: arrays} from record_libero_demos' files."""
    out = {}
    for task in tasks:
        with np.load(Path(out_dir) / task_file(task)) as data:
            out[task] = {k: data[k] for k in data.files}
    return out

"""Language grounding on LIBERO-Object: does the policy pick, and look at, the object the instruction names?

Per episode (a LIBERO task run whose instruction names an object: `envs.libero_tasks.named_object`):
- the named object's scene instance ("alphabet soup" -> "alphabet_soup_1", from the episode's object masks);
- the object picked, from the simulator state at the episode's end (episode.json "outcome", written by
  `LiberoEnv.episode_outcome`: the object in the basket, else the one held);
- the grasp step: the first step whose executed gripper command closes (< 0.5 in the "libero" action space);
- per layer and camera, the lift (attention mass / mask area; 1 = chance) of every object in the scene, averaged over
  the steps up to the grasp (all steps without one), and whether the named object got more attention mass than
  every other object at the grasp step. "Other" objects are the scene's graspable ones; the instruction's goal (the
  basket, which it names too) is kept apart (role "goal" in the per-object table).

`swap_rows` aggregates instruction swaps: episodes of scene task i told another instruction (a run's `--instruction`)
-> how often the picked object is the named one, the scene's own target, another object or none, with a Wilson
interval (kind "own", "paraphrase", "swap", or "names no object" for nonsense), against the language-blind rate:
how often the same policy, told the scene's own instruction on the same
initial states, picked the object the swapped instruction names (a policy that ignores the instruction picks as it
did there).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from harness.bounded import open_npz, read_json
from harness.measures.stats import wilson_interval

CLOSED_BELOW = 0.5  # the "libero" action space's gripper: 1 open, 0 closed (envs.actions.libero_action's binarising)
MASK_PREFIX = "object."


@dataclass
class GroundingEpisode:
    run: str
    task: str
    episode: int
    seed: int
    success: bool
    instruction: str
    named: str | None  # scene instance the instruction names
    scene_target: str | None  # the task's own target instance
    picked: str | None  # the object picked (outcome), None when none
    grasp_step: int  # -1: the gripper never closed
    objects: tuple[str, ...] = ()
    # {camera: (layers, objects) mean lift up to the grasp}; {camera: (layers,) bool} named mass > every other at grasp
    lifts: dict = field(default_factory=dict)
    top_at_grasp: dict = field(default_factory=dict)
    goals: tuple[str, ...] = ()  # the instruction's other objects of interest (the basket): neither named nor "other"


def instance_of(words: str | None, instances) -> str | None:
    """"alphabet soup" -> the instance "alphabet_soup_1" among `instances` (name without its trailing _<n>), else None."""
    if not words:
        return None
    stem = re.sub(r"\s+", "_", words.strip().lower())
    matches = [i for i in instances if re.sub(r"_\d+$", "", i) == stem]
    return matches[0] if len(matches) == 1 else None


def grasp_step(executed: np.ndarray) -> int:
    """First step whose executed gripper command (last column) closes; -1 when it never does."""
    executed = np.asarray(executed, np.float64)
    if executed.ndim != 2 or executed.shape[0] == 0:
        return -1
    closed = np.flatnonzero(executed[:, -1] < CLOSED_BELOW)
    return int(closed[0]) if closed.size else -1


STALL_QUIET = 0.3  # a translation command below this (of the OSC's [-1, 1]) on every axis: the hand barely moves
STALL_STEPS = 100  # a stall this long (5 s at 20 Hz) is counted as the episode's failure mode ("stalled open")


def longest_stall(executed: np.ndarray, quiet: float = STALL_QUIET) -> tuple[int, int]:
    """(first step, length) of the longest run of steps, after the first close, whose executed gripper command is
    open and whose translation commands are all below `quiet` in magnitude: the policy waiting open over the scene
    instead of grasping again. (0, 0) when there is none or the gripper never closes."""
    executed = np.asarray(executed, np.float64)
    first = grasp_step(executed)
    if first < 0 or executed.shape[1] < 4:
        return 0, 0
    waiting = (executed[first:, -1] >= CLOSED_BELOW) & (np.abs(executed[first:, :3]).max(axis=1) < quiet)
    edges = np.diff(np.concatenate([[0], waiting.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    if not starts.size:
        return 0, 0
    k = int(np.argmax(ends - starts))
    return first + int(starts[k]), int(ends[k] - starts[k])


def _object_measures(z, camera: str) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(object names, mass (steps, layers, objects), area (steps, objects)) of one camera from attention.npz."""
    prefix = f"measures/layer/mask_mass/{camera}/{MASK_PREFIX}"
    names = sorted(k[len(prefix):] for k in z.files if k.startswith(prefix))
    if not names:
        return [], np.zeros((0, 0, 0)), np.zeros((0, 0))
    mass = np.stack([np.asarray(z[prefix + n], np.float64) for n in names], axis=-1)
    area = np.stack([np.asarray(z[f"metrics/mask_area/{camera}/{MASK_PREFIX}{n}"], np.float64) for n in names], axis=-1)
    return names, mass, area


def episode_grounding(attention_path, actions_path, episode_json: dict, cameras=("image_primary", "image_wrist"),
                      goals=()):
    """(objects, {camera: (layers, objects) lift up to the grasp}, {camera: (layers,) named-on-top at the grasp},
    grasp step) for one episode; the named instance comes from `episode_json["instruction"]`. "On top": more mass
    than every other object except the `goals` (the basket, which the instruction names too)."""
    from envs.libero_tasks import named_object

    with open_npz(actions_path) as a:
        grasp = grasp_step(a["executed"]) if "executed" in a.files else -1
    lifts, top = {}, {}
    objects: list[str] = []
    words = named_object(str(episode_json.get("instruction", "")))
    with open_npz(attention_path) as z:
        for camera in cameras:
            names, mass, area = _object_measures(z, camera)
            if not names or mass.shape[0] == 0:
                continue
            objects = objects or names
            if names != objects:
                continue
            end = grasp + 1 if grasp >= 0 else mass.shape[0]
            with np.errstate(divide="ignore", invalid="ignore"):
                lift = np.where(area[:end, None, :] > 0, mass[:end] / area[:end, None, :], np.nan)
            lifts[camera] = np.nanmean(lift, axis=0) if np.isfinite(lift).any() else np.full(lift.shape[1:], np.nan)
            named = instance_of(words, names)
            if named is not None and grasp >= 0 and grasp < mass.shape[0]:
                at = mass[grasp]  # (layers, objects)
                i = names.index(named)
                others = np.delete(at, [j for j, n in enumerate(names) if j == i or n in goals], axis=-1)
                top[camera] = at[:, i] > (others.max(axis=-1) if others.size else -np.inf)
    return tuple(objects), lifts, top, grasp


def collect(records) -> tuple[list[GroundingEpisode], list[str]]:
    """Grounding rows of every finished episode of LIBERO tasks whose instruction names an object, and notes."""
    from envs.libero_tasks import get_libero_task, is_libero, named_object

    rows, notes = [], []
    for record in records:
        for e in record.episodes:
            if not is_libero(e.task) or not e.ok:
                continue
            try:
                meta = read_json(e.directory / "episode.json")
                if not isinstance(meta, dict):
                    raise ValueError("not a JSON object")
                spec = get_libero_task(e.task)
                goals = tuple(spec.targets[1:])
                objects, lifts, top, grasp = episode_grounding(e.attention_path, e.directory / "actions.npz", meta,
                                                               goals=goals)
            except (OSError, ValueError, KeyError) as exc:
                notes.append(f"{record.name}/{e.task}/episode_{e.episode}: unreadable ({str(exc).splitlines()[0]})")
                continue
            instruction = str(meta.get("instruction", ""))
            words = named_object(instruction)
            outcome = meta.get("outcome") if isinstance(meta.get("outcome"), dict) else {}
            if not objects:  # no object masks (a run with --no-masks): nothing to measure attention on
                objects = tuple(str(n) for n in outcome.get("objects", ()) if isinstance(n, str))
            picked = outcome.get("picked_object")
            target = spec.targets[0] if spec.targets else None
            rows.append(GroundingEpisode(record.name, e.task, e.episode, e.seed if e.seed is not None else -1,
                                         bool(e.success), instruction, instance_of(words, objects),
                                         target if target in objects else None,
                                         picked if isinstance(picked, str) else None, grasp, objects, lifts, top,
                                         goals))
    return rows, notes


LIFT_COLUMNS = ("run", "task", "camera", "layer", "episodes", "named_lift", "others_mean_lift", "others_max_lift",
                "named_over_others", "named_top_at_grasp", "grasped_episodes")
OBJECT_COLUMNS = ("run", "task", "camera", "layer", "object", "role", "episodes", "mean_lift")


def lift_rows(rows: list[GroundingEpisode]) -> tuple[list[tuple], list[tuple]]:
    """Per (run, task, camera, layer): named lift, the others' mean and max lift, their ratio, episodes where the named
    object got the most mass at the grasp; and per object (role "named", "goal" or "other") its mean lift."""
    summary, per_object = [], []
    groups: dict[tuple, list[GroundingEpisode]] = {}
    for r in rows:
        if r.named is not None and r.named == r.scene_target:  # the task's own instruction (swaps are in swap_rows)
            groups.setdefault((r.run, r.task), []).append(r)
    for (run, task), episodes in groups.items():
        cameras = sorted({c for r in episodes for c in r.lifts})
        for camera in cameras:
            have = [r for r in episodes if camera in r.lifts]
            objects = have[0].objects
            stack = np.stack([r.lifts[camera] for r in have if r.objects == objects])  # (episodes, layers, objects)
            named_index = objects.index(have[0].named)
            others = [i for i, name in enumerate(objects) if i != named_index and name not in have[0].goals]
            tops = [r.top_at_grasp[camera] for r in have if camera in r.top_at_grasp]
            for layer in range(stack.shape[1]):
                named = float(np.nanmean(stack[:, layer, named_index]))
                other = stack[:, layer, others]
                others_mean = float(np.nanmean(other)) if other.size else math.nan
                others_max = float(np.nanmax(np.nanmean(other, axis=0))) if other.size else math.nan
                top = int(sum(bool(t[layer]) for t in tops))
                summary.append((run, task, camera, layer, len(stack), named, others_mean, others_max,
                                named / others_mean if others_mean and math.isfinite(others_mean) else math.nan,
                                top, len(tops)))
                for i, name in enumerate(objects):
                    role = "named" if i == named_index else ("goal" if name in have[0].goals else "other")
                    per_object.append((run, task, camera, layer, name, role, len(stack),
                                       float(np.nanmean(stack[:, layer, i]))))
    return summary, per_object


SWAP_COLUMNS = ("run", "task", "instruction", "kind", "episodes", "picked_named", "rate", "ci_low", "ci_high",
                "picked_scene_target", "picked_other", "picked_none", "blind_rate", "blind_episodes")


def swap_rows(rows: list[GroundingEpisode], all_records=None) -> list[tuple]:
    """Per (run, task, instruction): the picked object against the named one; `kind` is "own" (the task's own
    instruction), "paraphrase" (another wording naming the same object) or "swap" (another object); the language-
    blind rate of a swap: how often the episodes of the same task and initial states under the task's own
    instruction picked the object this instruction names."""
    from envs.libero_tasks import get_libero_task

    own = {}
    for r in rows:
        if r.instruction == get_libero_task(r.task).instruction:
            own.setdefault(r.task, {})[r.seed] = r.picked
    groups: dict[tuple, list[GroundingEpisode]] = {}
    for r in rows:
        groups.setdefault((r.run, r.task, r.instruction), []).append(r)
    out = []
    for (run, task, instruction), episodes in groups.items():
        named = episodes[0].named
        if instruction == get_libero_task(task).instruction:
            kind = "own"
        elif named is None:
            kind = "names no object"  # a nonsense instruction, or one naming an object this scene lacks
        elif named is not None and named == episodes[0].scene_target:
            kind = "paraphrase"
        else:
            kind = "swap"
        n = len(episodes)
        hits = sum(r.picked is not None and r.picked == r.named for r in episodes)
        low, high = wilson_interval(hits, n)
        target = sum(r.picked is not None and r.picked == r.scene_target for r in episodes)
        none = sum(r.picked is None for r in episodes)
        paired = [own.get(task, {}).get(r.seed, "<missing>") for r in episodes]
        paired = [p for p in paired if p != "<missing>"]
        blind = (sum(p is not None and p == named for p in paired) / len(paired)) if paired else math.nan
        out.append((run, task, instruction, kind, n, hits, hits / n if n else math.nan, low, high, target,
                    n - hits - none - (target if named != episodes[0].scene_target else 0), none, blind, len(paired)))
    return out


def is_grounding(records) -> bool:
    """Whether any run holds LIBERO-Object episodes (the report then adds its Grounding section)."""
    return any(t.startswith("libero_object/") for r in records for t in r.tasks)

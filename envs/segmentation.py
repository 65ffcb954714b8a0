"""Target, robot, gripper and goal masks from MuJoCo segmentation renders, through lookup tables (pure numpy).

A segmentation render (mjRND_SEGMENT + mjRND_IDCOLOR) paints every pixel with `segid + 1` of the scene
geom that covers it, encoded as r + 256 g + 65536 b (0 = background). Each scene geom names the model
object it came from (objtype, objid). `geom_categories` labels every model geom once per model
(target / goal / gripper / robot / other); `scene_lookup` turns one render's scene into a `segid + 1 -> category` table;
`masks_from_segmentation` is then a single numpy gather per image, with no per-pixel Python.

A change to what a label covers changes the stored measures: bump harness.measures.attention.MEASURES_VERSION.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

OTHER, TARGET, ROBOT, GRIPPER, GOAL = 0, 1, 2, 3, 4  # GRIPPER: the hand and fingers, part of the robot
TASK_OBJECT = 5  # an object of the task other than the target and the goal (PickPlace's other objects)
DISTRACTOR = 16  # distractor i is labelled DISTRACTOR + i (envs.perturbations adds them)
MJOBJ_GEOM = 5  # mujoco.mjtObj.mjOBJ_GEOM


def body_ancestry_matches(body_names: Sequence[str], body_parentid: np.ndarray, prefixes: Sequence[str]) -> np.ndarray:
    """(nbody,) bool: the body or one of its ancestors (world excluded) has a name starting with a prefix."""
    prefixes = tuple(prefixes)
    own = np.array([bool(prefixes) and (name or "").startswith(prefixes) for name in body_names], dtype=bool)
    result = own.copy()
    for body in range(len(body_names)):  # bodies are stored parents-first, so one pass suffices
        parent = int(body_parentid[body])
        if body != 0 and parent != 0:
            result[body] |= result[parent]
    return result


def geom_categories(
    geom_bodyid: np.ndarray, body_names: Sequence[str], body_parentid: np.ndarray, target_prefixes: Sequence[str],
    robot_prefixes: Sequence[str], gripper_prefixes: Sequence[str] = (), goal_prefixes: Sequence[str] = (),
) -> np.ndarray:
    """(ngeom,) uint8 category of every model geom: TARGET, GOAL, GRIPPER, ROBOT or OTHER, in that precedence.

    GRIPPER marks robot bodies (the hand and its fingers) under `gripper_prefixes`; a body there that is not
    also under a robot prefix stays OTHER, so the gripper always lies inside the robot."""
    target_bodies = body_ancestry_matches(body_names, body_parentid, target_prefixes)
    goal_bodies = body_ancestry_matches(body_names, body_parentid, goal_prefixes)
    robot_bodies = body_ancestry_matches(body_names, body_parentid, robot_prefixes)
    gripper_bodies = body_ancestry_matches(body_names, body_parentid, gripper_prefixes) & robot_bodies
    body_category = np.select([target_bodies, goal_bodies, gripper_bodies, robot_bodies],
                              [TARGET, GOAL, GRIPPER, ROBOT], OTHER).astype(np.uint8)  # (nbody,)
    return body_category[np.asarray(geom_bodyid)]


def scene_lookup(segids: np.ndarray, objtypes: np.ndarray, objids: np.ndarray, geom_category: np.ndarray) -> np.ndarray:
    """(max segid + 2,) uint8 table from decoded pixel id (segid + 1) to category, for one rendered scene.

    segids, objtypes, objids: (scene_geoms,) of the scene that was rendered; non-geom scene objects
    (sites, decorations) and hidden geoms (segid -1) map to OTHER.
    """
    segids = np.asarray(segids)
    size = int(segids.max()) + 2 if len(segids) else 1
    table = np.zeros(size, dtype=np.uint8)
    shown = (segids >= 0) & (np.asarray(objtypes) == MJOBJ_GEOM)
    table[segids[shown] + 1] = np.asarray(geom_category)[np.asarray(objids)[shown]]
    return table


def decode_ids(segmentation_rgb: np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8 id-colour render -> (h, w) int64 pixel ids (segid + 1; 0 = background)."""
    rgb = segmentation_rgb.astype(np.int64)
    return rgb[..., 0] + (rgb[..., 1] << 8) + (rgb[..., 2] << 16)


def masks_from_segmentation(segmentation_rgb: np.ndarray, table: np.ndarray, gripper: bool = False,
                            goal: bool = False) -> dict[str, np.ndarray]:
    """(h, w, 3) id-colour render + lookup table -> {"target": (h, w) bool, "robot": (h, w) bool} (the robot with
    its gripper), plus "gripper" (hand and fingers) and "arm" (the robot without them) when `gripper`, and "goal"
    when `goal` (the task has a goal region)."""
    return _masks(_labels(segmentation_rgb, table), gripper, goal)


def scene_labels(geom_category: np.ndarray, geom_bodyid: np.ndarray, body_names: Sequence[str], body_parentid: np.ndarray,
                 task_object_prefixes: Sequence[str], distractor_prefixes: Sequence[str]) -> np.ndarray:
    """(ngeom,) uint8 label of every model geom: the categories of `geom_categories` (TARGET, GOAL, GRIPPER, ROBOT),
    else TASK_OBJECT under a task object prefix, DISTRACTOR + i under distractor prefix i, else OTHER (the arena:
    table, floor, walls, bins that are not the goal)."""
    labels = np.asarray(geom_category, dtype=np.uint8).copy()
    free = labels == OTHER
    bodies = np.asarray(geom_bodyid)
    task = body_ancestry_matches(body_names, body_parentid, task_object_prefixes)[bodies]
    labels[free & task] = TASK_OBJECT
    for i, prefix in enumerate(distractor_prefixes):
        labels[free & body_ancestry_matches(body_names, body_parentid, (prefix,))[bodies]] = DISTRACTOR + i
    return labels


def labelled_masks(segmentation_rgb: np.ndarray, table: np.ndarray, distractors: int = 0, gripper: bool = False,
                   goal: bool = False) -> dict[str, np.ndarray]:
    """(h, w, 3) id-colour render + a `scene_lookup` table of `scene_labels` -> the masks of
    `masks_from_segmentation`, plus "background" and "distractor_<i>" for i < distractors: (h, w) bool.
    Background: pixels of no robot, target, goal, task object or distractor (the arena, and pixels no geom covers)."""
    label = _labels(segmentation_rgb, table)
    out = _masks(label, gripper, goal)
    out["background"] = label == OTHER
    for i in range(distractors):
        out[f"distractor_{i}"] = label == DISTRACTOR + i
    return out


def _labels(segmentation_rgb: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(h, w) uint8 label of every pixel of an id-colour render."""
    ids = decode_ids(segmentation_rgb)
    return table[np.where(ids < len(table), ids, 0)]


def _masks(label: np.ndarray, gripper: bool, goal: bool) -> dict[str, np.ndarray]:
    out = {"target": label == TARGET, "robot": (label == ROBOT) | (label == GRIPPER)}
    if gripper:
        out["gripper"] = label == GRIPPER
        out["arm"] = label == ROBOT
    if goal:
        out["goal"] = label == GOAL
    return out

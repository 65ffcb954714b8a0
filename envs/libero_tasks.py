"""LIBERO's suites as harness tasks: "libero_object/3" is task 3 of LIBERO-Object, "libero_object" the whole suite.

The table (suites, task names, instructions, BDDL objects of interest, stored initial states) is
envs/libero_tasks.json, written from the installed package by scripts/libero_tasks.py and checked against it by
tests/libero/test_libero_env.py, so listing and validating tasks needs no LIBERO environment. Step limits are the published
evaluation's (OpenVLA's run_libero_eval.py: the longest training demonstration plus a margin), counted after the
settle steps.
"""

from __future__ import annotations

import functools
import json
import re
from pathlib import Path

from envs.taskspec import TaskSpec, UnknownTaskError

# policy steps per episode, after the settle steps (OpenVLA's LIBERO evaluation)
STEP_LIMITS = {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520, "libero_90": 400}
SUITES = tuple(STEP_LIMITS)  # in listing order; libero_90 last
SETTLE_STEPS = 10  # no-op actions (arm still, gripper open) after restoring the initial state: objects drop and settle
TABLE_PATH = Path(__file__).with_name("libero_tasks.json")


@functools.lru_cache(maxsize=1)
def _table() -> dict:
    return json.loads(TABLE_PATH.read_text())


# Paraphrases of LIBERO-Object's instructions ("pick up the X and place it in the basket"): the same task in other
# words, used by the reference policy's training (reference_policies.libero_demos) and `--perturb language`.
_OBJECT_INSTRUCTION = re.compile(r"^pick up the (?P<object>.+) and place it in the basket$")
_OBJECT_PARAPHRASES = ("put the {object} in the basket", "place the {object} into the basket",
                       "grab the {object} and drop it in the basket", "move the {object} to the basket")


def paraphrases(instruction: str) -> tuple[str, ...]:
    """Paraphrases of a LIBERO instruction: LIBERO-Object's pattern has four; other instructions have none."""
    match = _OBJECT_INSTRUCTION.match(instruction)
    return tuple(p.format(object=match["object"]) for p in _OBJECT_PARAPHRASES) if match else ()


def named_object(instruction: str) -> str | None:
    """The object a LIBERO-Object instruction (or one of its paraphrases) names ("alphabet soup"), else None."""
    for pattern in (_OBJECT_INSTRUCTION, *(re.compile("^" + re.escape(p).replace(r"\{object\}", "(?P<object>.+)") + "$")
                                           for p in _OBJECT_PARAPHRASES)):
        match = pattern.match(instruction.strip().lower())
        if match:
            return match["object"]
    return None


@functools.lru_cache(maxsize=1)
def libero_tasks() -> tuple[TaskSpec, ...]:
    """Every LIBERO task of the five suites as a TaskSpec (targets: the BDDL objects of interest)."""
    specs = []
    for suite in SUITES:
        for index, task in enumerate(_table()["suites"][suite]):
            specs.append(TaskSpec(
                name=f"{suite}/{index}", robosuite_env="libero", instruction=task["instruction"],
                paraphrases=paraphrases(task["instruction"]),
                targets=tuple(task["objects_of_interest"]), max_episode_steps=STEP_LIMITS[suite],
                simulator="libero", initial_states=int(task["initial_states"])))
    return tuple(specs)


def is_libero(name: str) -> bool:
    """Whether `name` names a LIBERO suite or task (by its prefix; it may still be out of range)."""
    return name.strip().lower().split("/")[0] in SUITES


def suite_and_index(name: str) -> tuple[str, int]:
    """"libero_object/3" -> ("libero_object", 3)."""
    suite, _, index = name.partition("/")
    return suite, int(index)


def expand(name: str) -> list[str]:
    """A suite name -> its task names in order; a task name -> [itself]; anything wrong -> UnknownTaskError."""
    text = name.strip().lower()
    suite, slash, index = text.partition("/")
    if suite not in SUITES:
        raise UnknownTaskError(f"unknown LIBERO suite {suite!r}; suites: {', '.join(SUITES)}")
    count = len(_table()["suites"][suite])
    if not slash:
        return [f"{suite}/{i}" for i in range(count)]
    if not index.isdigit() or int(index) >= count:
        raise UnknownTaskError(f"{name!r}: {suite} has tasks {suite}/0 to {suite}/{count - 1}")
    return [f"{suite}/{int(index)}"]


def get_libero_task(name: str) -> TaskSpec:
    (canonical,) = expand(name)
    suite, index = suite_and_index(canonical)
    offset = sum(len(_table()["suites"][s]) for s in SUITES[:SUITES.index(suite)])
    return libero_tasks()[offset + index]


def suite_table() -> str:
    """Plain-text listing of the LIBERO suites and their tasks for `octo-harness tasks`."""
    lines = []
    for suite in SUITES:
        tasks = _table()["suites"][suite]
        lines.append(f"{suite} ({len(tasks)} tasks, {STEP_LIMITS[suite]} steps; --task {suite} runs them all)")
        for index, task in enumerate(tasks):
            lines.append(f"  {suite}/{index:<3} {task['instruction']}  [targets: {', '.join(task['objects_of_interest'])}]")
    return "\n".join(lines)

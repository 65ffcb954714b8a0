"""Task registry: which robosuite environments the harness offers, with instruction, targets and episode length.

Every single-arm robosuite 1.5 manipulation task that loads with a Panda is listed. `targets` are
body-name prefixes: a MuJoCo geom belongs to a target when its body or one of the body's ancestors has
a name starting with one of them (robosuite names an object's bodies `<object>_...`). Targets are the
object(s) the robot has to grasp, push or move, so that attention on them can be measured. `goal` prefixes
name where the target has to go (Stack: cubeB; the PickPlace tasks: bin2, the bin the objects go to; the nut
tasks: the nut's peg), for the goal mask; empty where the task has no goal region. A task's phases (approach,
grasp, ...) are read off the simulator state by `envs.phases`.
A task is an `envs.taskspec.TaskSpec`; this is the robosuite suite's listing (envs.robosuite_suite), and
`envs.resolver.get_task` finds a task by name in any registered suite (envs.suites).
"""

from __future__ import annotations

from envs.taskspec import TaskSpec

_TASKS: tuple[TaskSpec, ...] = (
    TaskSpec(
        "Lift",
        "Lift",
        "pick up the red cube",
        ("lift the red cube", "grasp the red block and raise it", "pick the red block up off the table"),
        ("cube_",),
        300,
    ),
    TaskSpec(
        "Stack",
        "Stack",
        "stack the red cube on the green cube",
        ("put the red block on top of the green block", "place the red cube onto the green cube", "stack red on green"),
        ("cubeA_",),
        400,
        goal=("cubeB_",),
    ),
    TaskSpec(
        "PickPlaceCan",
        "PickPlaceCan",
        "put the can in its bin",
        ("pick up the can and place it in the bin", "move the soda can into the right bin", "place the can in the bin"),
        ("Can_",),
        400,
        goal=("bin2",),
    ),
    TaskSpec(
        "PickPlaceMilk",
        "PickPlaceMilk",
        "put the milk carton in its bin",
        ("pick up the milk and place it in the bin", "move the milk carton into the right bin", "place the milk in the bin"),
        ("Milk_",),
        400,
        goal=("bin2",),
    ),
    TaskSpec(
        "PickPlaceBread",
        "PickPlaceBread",
        "put the bread in its bin",
        ("pick up the bread and place it in the bin", "move the loaf of bread into the right bin", "place the bread in the bin"),
        ("Bread_",),
        400,
        goal=("bin2",),
    ),
    TaskSpec(
        "PickPlaceCereal",
        "PickPlaceCereal",
        "put the cereal box in its bin",
        ("pick up the cereal box and place it in the bin", "move the cereal into the right bin", "place the cereal in the bin"),
        ("Cereal_",),
        400,
        goal=("bin2",),
    ),
    TaskSpec(
        "PickPlace",
        "PickPlace",
        "put each object in its bin",
        ("sort the milk, bread, cereal and can into the bins", "place every object in its bin", "move all four objects into the bins"),
        ("Milk_", "Bread_", "Cereal_", "Can_"),
        1000,
        goal=("bin2",),
    ),
    TaskSpec(
        "NutAssemblySquare",
        "NutAssemblySquare",
        "put the square nut on the square peg",
        ("place the square nut onto the square peg", "fit the square nut over the square peg", "move the square nut to its peg"),
        ("SquareNut_",),
        500,
        goal=("peg1",),
    ),
    TaskSpec(
        "NutAssemblyRound",
        "NutAssemblyRound",
        "put the round nut on the round peg",
        ("place the round nut onto the round peg", "fit the round nut over the round peg", "move the round nut to its peg"),
        ("RoundNut_",),
        500,
        goal=("peg2",),
    ),
    TaskSpec(
        "NutAssembly",
        "NutAssembly",
        "put each nut on its matching peg",
        ("place the square nut and the round nut on their pegs", "fit both nuts over their pegs", "assemble the nuts onto the pegs"),
        ("SquareNut_", "RoundNut_"),
        800,
        goal=("peg1", "peg2"),
    ),
    TaskSpec(
        "Door",
        "Door",
        "open the door",
        ("turn the handle and pull the door open", "open the door by its handle", "pull the door open"),
        ("Door_latch",),
        400,
        primary_camera="sideview",  # robosuite's agentview sits behind the robot base in this arena
    ),
    TaskSpec(
        "Wipe",
        "Wipe",
        "wipe the dirt off the table",
        ("clean the markings on the table", "wipe the table clean", "scrub away the dirt on the table"),
        ("contact",),
        500,
    ),
    TaskSpec(
        "ToolHang",
        "ToolHang",
        "insert the hook into the stand and hang the tool on it",
        ("put the frame into the stand, then hang the tool on the hook", "assemble the hook and hang the wrench on it", "hang the tool"),
        ("frame_", "tool_"),
        700,
    ),
)

def list_tasks() -> list[TaskSpec]:
    """Every registered task, in registry order."""
    return list(_TASKS)


def task_table(tasks: list[TaskSpec] | None = None, all_suites: bool = False) -> str:
    """A plain-text table of tasks (name, max steps, targets, instruction) for `octo-harness tasks`; with `all_suites`,
    every registered suite's listing after it (envs.suites: LIBERO's suites and tasks, which run in LIBERO's own
    environment, docs/libero.md; a registered suite's own)."""
    from envs import suites

    if all_suites and tasks is None:
        return "\n\n".join(suite.table() for suite in suites.suites())
    return suites.task_table(list_tasks() if tasks is None else tasks)

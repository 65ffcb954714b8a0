"""Task phases read off the simulator's privileged state (never off the policy or an expert).

A phase function maps a `PhaseState` (what the simulator knows about the object to move and its goal) to one
of the task's phases, in order:

  Lift:                         approach, grasp, lift
  Stack, PickPlace<Obj>, nut:   approach, grasp, transport, place, release

  place      the object is over its goal in x and y (Stack: within cubeB's half size; PickPlace: over its bin
             region; nuts: within 3 cm of the peg, as robosuite's `on_peg`) and the gripper holds it
  release    the same, but the gripper does not hold it while it is lifted or rests on its goal (Stack: cubeA
             touches cubeB; PickPlace: inside its bin's region; nuts: on their peg): the fingers have let go
  transport  the object is lifted (its centre more than `LIFTED` above where it rested at reset)
  lift       (Lift) the same: lifted
  grasp      robosuite's own grasp check (`_check_grasp`: both finger pads touch the object) holds
  approach   none of the above

The first rule that holds wins. The function is memoryless (a dropped object goes back to approach); the
episode's furthest phase is the maximum over its states. Tasks without a phase function (PickPlace with four
objects, NutAssembly with two nuts, Door, Wipe, ToolHang) record no phase (null).

A change to a phase rule changes the stored measures: bump harness.measures.attention.MEASURES_VERSION.
"""

from __future__ import annotations

from dataclasses import dataclass

LIFTED = 0.01  # metres above the object's rest height (its centre at reset) from which it counts as lifted
PICK_PLACE = ("approach", "grasp", "transport", "place", "release")
LIFT = ("approach", "grasp", "lift")


@dataclass(frozen=True)
class PhaseState:
    """What a phase function reads: privileged simulator state of the object to move and its goal."""

    grasped: bool  # robosuite's _check_grasp of the object
    lift: float  # metres the object's centre is above its height at reset
    over_goal: bool = False  # object over its goal in x, y
    on_goal: bool = False  # object resting on / inside its goal


@dataclass(frozen=True)
class PhaseSpec:
    """A task's phases: the robosuite object to move, where it goes (None: no goal), and the phase names in order."""

    obj: str  # robosuite object name (RobosuiteEnv.object_poses keys): "cube", "cubeA", "Can", "SquareNut", ...
    goal: str | None  # "cubeB", "bin", "peg1", "peg2" or None
    names: tuple[str, ...]


PHASE_SPECS: dict[str, PhaseSpec] = {
    "Lift": PhaseSpec("cube", None, LIFT),
    "Stack": PhaseSpec("cubeA", "cubeB", PICK_PLACE),
    "PickPlaceCan": PhaseSpec("Can", "bin", PICK_PLACE),
    "PickPlaceMilk": PhaseSpec("Milk", "bin", PICK_PLACE),
    "PickPlaceBread": PhaseSpec("Bread", "bin", PICK_PLACE),
    "PickPlaceCereal": PhaseSpec("Cereal", "bin", PICK_PLACE),
    "NutAssemblySquare": PhaseSpec("SquareNut", "peg1", PICK_PLACE),
    "NutAssemblyRound": PhaseSpec("RoundNut", "peg2", PICK_PLACE),
}
NO_PHASES = ("PickPlace", "NutAssembly", "Door", "Wipe", "ToolHang")  # several objects, or no object to carry


def phase_names(task: str) -> tuple[str, ...]:
    """The task's phases in order; () for a task without a phase function."""
    spec = PHASE_SPECS.get(task)
    return spec.names if spec is not None else ()


def phase_of(names: tuple[str, ...], state: PhaseState) -> str:
    """The phase (one of `names`, LIFT or PICK_PLACE) of one state; see the module docstring for the rules."""
    lifted = state.lift > LIFTED
    if names == LIFT:
        return "lift" if lifted else "grasp" if state.grasped else "approach"
    if names != PICK_PLACE:
        raise ValueError(f"no phase rules for phases {names}")
    if state.over_goal and (state.grasped or lifted or state.on_goal):
        return "place" if state.grasped else "release"
    if lifted:
        return "transport"
    return "grasp" if state.grasped else "approach"


def phase_index(names: tuple[str, ...], phase: str | None) -> int:
    """Position of `phase` in `names` (-1 for None or a phase not in the list)."""
    return names.index(phase) if phase in names else -1

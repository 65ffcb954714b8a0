"""`octo-harness robustness`: a grid of perturbation kinds x levels x tasks run into one folder of runs, resumable.

The grid is one run per (kind, level > 0), each over every task, plus one nominal run that stands for level 0 of
every kind (a protocol whose perturbations are all at level 0 IS the nominal protocol: same hash, same frames):

    <out>/nominal/            the nominal protocol
    <out>/<kind>-<level>/     --perturb <kind>:<level> (camera@image_wrist -> camera@image_wrist-3)
    <out>/robustness.json     the grid: kinds, levels, tasks and {run name: perturb}

`camera` and `noise` without @KEY expand to one condition per camera the model reads (`expand_conditions`:
`camera` -> camera@image_primary, camera@image_wrist), so a grid moves every camera, not only the primary one.
A run whose perturbation a grid file already records under another name keeps that name (a grid made before
the expansion, with `camera-3` for camera@image_primary:3, resumes instead of running it again).

Every run goes through `harness.run.execute`, so running the same command again resumes each run where it stopped
and skips finished ones; the model is loaded once for the whole grid.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

from envs.perturbations import KEYED_KINDS, KINDS, LEVELS, PerturbationError, parse_perturb
from harness.analysis.compare import GRID_FILE  # the grid's robustness.json, read by compare and regress
from harness.analysis.compare_result import RobustnessGrid
from harness.files import atomic_write_json
from harness.run.protocol import Protocol

log = logging.getLogger(__name__)
NOMINAL = "nominal"
GRID_FORMAT = "octo-harness-robustness/1"


def parse_kinds(text: str | list) -> tuple[str, ...]:
    """"camera,lighting,camera@image_wrist" -> conditions (kind or kind@KEY), checked; one line on a bad one."""
    items = [t.strip() for item in (text if isinstance(text, list) else [text]) for t in str(item).split(",") if t.strip()]
    if not items:
        raise PerturbationError(f"--perturb names no kind; kinds: {', '.join(KINDS)}")
    for item in items:
        parse_perturb(f"{item}:1")  # the same checks as a run's --perturb
        if item.split("@")[0] not in KINDS:
            raise PerturbationError(f"--perturb {item!r}: unknown kind; kinds: {', '.join(KINDS)}")
    if len(set(items)) != len(items):
        raise PerturbationError(f"--perturb {','.join(items)}: a kind is given twice")
    return tuple(items)


def parse_levels(text: str) -> tuple[int, ...]:
    try:
        levels = sorted({int(x) for x in str(text).split(",") if x.strip()})
    except ValueError:
        raise PerturbationError(f"--levels takes comma-separated integers 0-5, got {text!r}") from None
    if not levels or any(level not in LEVELS for level in levels):
        raise PerturbationError(f"--levels takes comma-separated integers 0-5, got {text!r}")
    return tuple(levels)


def expand_conditions(conditions: tuple[str, ...], camera_keys) -> tuple[str, ...]:
    """Conditions with each bare keyed kind (`camera`, `noise`) replaced by one `kind@KEY` per camera key the model
    reads (in the model's order); explicit `kind@KEY` conditions and the other kinds stay; no duplicates."""
    out = []
    for condition in conditions:
        if condition in KEYED_KINDS and camera_keys:
            out += [f"{condition}@{key}" for key in camera_keys]
        else:
            out.append(condition)
    return tuple(dict.fromkeys(out))


def model_camera_keys(model) -> tuple[str, ...]:
    """The image observation keys a loaded model reads (`image_primary`, `image_wrist`, ...), in its order."""
    return tuple(k for k in getattr(model, "image_sizes", {}) if k.startswith("image_"))


def run_name(condition: str, level: int) -> str:
    return NOMINAL if level == 0 else f"{condition}-{level}"


def grid(conditions: tuple[str, ...], levels: tuple[int, ...]) -> dict[str, str | None]:
    """{run name: --perturb text or None (nominal)}, nominal first, then kind by kind, level by level."""
    runs: dict[str, str | None] = {NOMINAL: None} if 0 in levels else {}
    for condition in conditions:
        for level in levels:
            if level > 0:
                runs[run_name(condition, level)] = f"{condition}:{level}"
    return runs


def run_grid(base: Protocol, conditions: tuple[str, ...], levels: tuple[int, ...], out: Path, *, executor=None,
             model=None, progress: bool = True, overwrite: bool = False) -> dict:
    """Run (or resume) every run of the grid into `out`; returns {run name: RunSummary}."""
    from harness.run import checks
    from harness.run.driver import execute

    for perturb in grid(conditions, levels).values():  # cheap checks of what was asked, before loading the model
        checks.check_perturbations(base.replace(perturb=perturb))
    out = Path(out)
    existing = out / GRID_FILE
    old = None
    if existing.is_file() and not overwrite:
        from harness.bounded import BoundsError, read_json

        try:
            old = read_json(existing)
        except BoundsError:
            raise
        except (OSError, ValueError):
            old = None
        if not isinstance(old, dict) or old.get("format") != GRID_FORMAT:
            raise ValueError(f"{existing} is not a robustness grid file; choose another --out")
        try:
            old = RobustnessGrid.from_json({"runs": {}, **old})
        except (TypeError, ValueError):
            raise ValueError(f"{existing} is not a robustness grid file; choose another --out") from None
    if model is None:
        from harness.run.protocol import load_protocol_policy

        model = load_protocol_policy(base)
    conditions = expand_conditions(conditions, model_camera_keys(model))
    runs = grid(conditions, levels)
    if old is not None:  # a perturbation the grid already holds keeps its run's name
        known = {perturb: name for name, perturb in (old.runs or {}).items()}
        runs = {known.get(perturb, name): perturb for name, perturb in runs.items()}
    protocols = {name: base.replace(perturb=perturb) for name, perturb in runs.items()}
    for protocol in protocols.values():  # every task x camera checked before anything runs
        checks.check_perturbations(protocol)
    out.mkdir(parents=True, exist_ok=True)
    record = RobustnessGrid(format=GRID_FORMAT, conditions=tuple(conditions), levels=tuple(levels),
                            tasks=tuple(base.tasks), runs=runs)
    if old is not None:  # a grid may grow by kinds or levels
        record = replace(record, runs={**(old.runs or {}), **runs},
                         conditions=tuple(dict.fromkeys([*(old.conditions or ()), *conditions])),
                         levels=tuple(sorted(set(old.levels or ()) | set(levels))))
    atomic_write_json(existing, record.to_json())
    summaries = {}
    for name, protocol in protocols.items():
        log.info("robustness: run %s (%s)", name, protocol.perturb or "nominal")
        summaries[name] = execute(protocol, out, name, overwrite=overwrite, executor=executor, model=model,
                                  progress=progress)
    return summaries


def keyed(condition: str) -> bool:
    return condition.split("@")[0] in KEYED_KINDS

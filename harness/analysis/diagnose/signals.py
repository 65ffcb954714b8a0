"""The per-step signals `diagnose` reads from finished run folders, each known at step t from steps <= t only.

Per finished episode (`EpisodeSignals`), one value per step 0..steps-1:
  phase        the task phase's index (attention.npz `phase` into `phase_names`; -1 without phases: Door, LIBERO)
  entropy      attention entropy of the readout rows, the model's last layer (attention.npz measures/layer/entropy)
  nuisance     attention mass on the background plus every distractor, primary camera, last layer
  target, gripper  attention mass on the target and the gripper, primary camera, last layer
  consistency  the action chunk's disagreement with the earlier chunks' plans (action_consistency.npz, or computed
               from actions.npz where the run had no --action-consistency), held from its last inferred step
  reliance     nuisance reliance (reliance.jsonl, --reliance-every), held from its last sampled step
and the readout features (readout_features.npz, --readout-features-every), held likewise. A signal an episode does
not have is nan throughout.

`load(paths)` expands a robustness grid folder (robustness.json) into its condition runs and reads every finished
episode (status ok) of every run.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from harness.analysis.compare import GRID_FILE, read_grid
from harness.analysis.robustness import run_condition
from harness.analysis.robustness_measures import CAMERA
from harness.analysis.runs import EpisodeRecord, RunRecord, load_run, read_npz
from harness.probes import registry as probes

SIGNALS = ("entropy", "nuisance", "target", "gripper", "consistency", "reliance")


@dataclass(eq=False)
class EpisodeSignals:
    run: str
    task: str
    condition: str  # "nominal" or e.g. "camera@image_wrist:3"
    seed: int
    episode: int
    success: bool
    steps: int
    phase_names: tuple[str, ...]
    phase: np.ndarray  # (steps,) int, -1 where unknown
    signals: dict[str, np.ndarray]  # SIGNALS -> (steps,) float64
    features: np.ndarray | None = None  # (steps, width) float32, held from the last recorded step; nan before it
    preflight: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def stratum(self) -> tuple[str, str]:
        """Within conditions: one run (one condition and level) and one task."""
        return (self.run, self.task)

    @property
    def has_phases(self) -> bool:
        return bool(self.phase_names) and bool((self.phase >= 0).any())


def held(steps: int, at, values: np.ndarray) -> np.ndarray:
    """Values recorded at steps `at` -> (steps, ...) with each step holding the last value recorded at or before it
    (nan before the first): what is known at step t."""
    values = np.asarray(values, np.float64)
    out = np.full((steps,) + values.shape[1:], np.nan)
    at = np.asarray(at, int)
    if not len(at):
        return out
    order = np.argsort(at, kind="stable")
    at, values = at[order], values[order]
    index = np.searchsorted(at, np.arange(steps), side="right") - 1
    known = index >= 0
    out[known] = values[index[known]]
    return out


def preflight_text(manifest: dict) -> str:
    """The run's pre-flight verdicts in one cell: 'check verdict; ...' (manifest "preflight"), or 'not run'."""
    found = (manifest.get("preflight") or {}) if isinstance(manifest, dict) else {}
    findings = found.get("findings") if isinstance(found, dict) else None
    if not findings:
        return "not run"
    return "; ".join(f"{f.get('check', '?')} {f.get('verdict', '?')}" for f in findings if isinstance(f, dict))


def expand(paths) -> list[Path]:
    """Run folders: each path as is, or a robustness grid folder's condition runs (in the grid's order)."""
    out = []
    for path in map(Path, paths):
        if (path / GRID_FILE).is_file():
            out += [path / name for name in read_grid(path).runs]
        else:
            out.append(path)
    return out


def _attention(directory: Path, steps: int) -> tuple[tuple[str, ...], np.ndarray, dict[str, np.ndarray]]:
    """attention.npz -> (phase names, phase (steps,), {entropy, nuisance, target, gripper: (steps,)})."""
    nan = np.full(steps, np.nan)
    path = directory / "attention.npz"
    if not path.is_file():
        return (), np.full(steps, -1), {}
    from harness.bounded import open_npz

    with open_npz(path) as z:
        names = set(z.files)
    wanted = [n for n in names if n in ("step", "phase", "phase_names", "measures/layer/entropy")
              or n.startswith(f"measures/layer/mask_mass/{CAMERA}/")]
    arrays = read_npz(path, *wanted, steps=steps)
    step = np.asarray(arrays.get("step", np.arange(steps)), int)
    inside = (step >= 0) & (step < steps)
    for key, value in arrays.items():  # an edited file: one line naming it (the report leaves the episode out)
        if key != "phase_names" and np.ndim(value) and len(value) != len(step):
            raise ValueError(f"{path}: {key} has {len(value)} rows for {len(step)} recorded steps; re-run that "
                             "episode (octo-harness run --resume RUN_DIR runs damaged episodes again)")

    def last_layer(key: str) -> np.ndarray | None:
        if key not in arrays:
            return None
        value = np.asarray(arrays[key], np.float64)
        value = value[:, -1] if value.ndim == 2 else value
        out = nan.copy()
        out[step[inside]] = value[inside]
        return out

    phase = np.full(steps, -1)
    if "phase" in arrays:
        phase[step[inside]] = np.asarray(arrays["phase"], int)[inside]
    names_ = tuple(str(n) for n in arrays.get("phase_names", ()))
    mass = f"measures/layer/mask_mass/{CAMERA}/"
    out = {"entropy": last_layer("measures/layer/entropy"), "target": last_layer(mass + "target"),
           "gripper": last_layer(mass + "gripper")}
    background = last_layer(mass + "background")
    if background is not None:
        distractors = [last_layer(k) for k in arrays if k.startswith(mass + "distractor_")]
        out["nuisance"] = background + sum(distractors, np.zeros(steps))
    return names_, phase, {k: v for k, v in out.items() if v is not None}


def _consistency(directory: Path, steps: int) -> np.ndarray | None:
    consistency_reader = probes.part("action_consistency", "reader")  # through the registry, as every consumer
    stored = consistency_reader.arrays(directory)
    if stored is None and (directory / "actions.npz").is_file():
        stored = consistency_reader.from_actions(directory)
    if stored is None or not len(stored["step"]):
        return None
    return held(steps, stored["step"], stored["disagreement"])


def _reliance(directory: Path, steps: int) -> np.ndarray | None:
    reliance_reader = probes.part("reliance", "reader")

    path = directory / reliance_reader.FILE
    if not path.is_file():
        return None
    found = reliance_reader.nuisance_reliance(reliance_reader.read_rows(path))
    return held(steps, found["step"], found["per_step"]) if found["step"] else None


def episode_signals(record: RunRecord, episode: EpisodeRecord, condition: str, preflight: str,
                    features: bool = True) -> EpisodeSignals:
    """One finished episode's signals; `features=False` leaves the readout features unread (the report's Failures
    section explains failures and predicts nothing)."""
    steps = int(episode.steps)
    directory = episode.directory
    names, phase, signals = _attention(directory, steps)
    consistency = _consistency(directory, steps)
    reliance = _reliance(directory, steps)
    for name, value in (("consistency", consistency), ("reliance", reliance)):
        if value is not None:
            signals[name] = value
    signals = {name: signals.get(name, np.full(steps, np.nan)) for name in SIGNALS}
    held_features = None
    found = probes.part("readout_features", "reader").arrays(directory) if features else None
    if found is not None and len(found[0]):
        held_features = held(steps, *found).astype(np.float32)
    return EpisodeSignals(record.name, episode.task, condition, -1 if episode.seed is None else int(episode.seed),
                          episode.episode, bool(episode.success), steps, names, phase, signals, held_features, preflight)


def condition_name(manifest: dict) -> str:
    found = run_condition(manifest)
    if found is None:
        return "several perturbations"
    return "nominal" if found == ("nominal", 0) else f"{found[0]}:{found[1]}"


def load(paths) -> tuple[list[EpisodeSignals], list[RunRecord], list[str]]:
    """Every finished episode (status ok, steps > 0) of the runs `paths` name (grids expanded), the run records, and
    notes (episodes left out and why). Two runs with one name are one line (ValueError)."""
    episodes, records, notes = [], [], []
    for path in expand(paths):
        record = load_run(path)
        if record.name in {r.name for r in records}:
            raise ValueError(f"two runs are named {record.name} ({path}); diagnose each grid or set of runs apart")
        records.append(record)
        condition, preflight = condition_name(record.manifest), preflight_text(record.manifest)
        for episode in record.episodes:
            if not episode.ok or episode.steps <= 0:
                notes.append(f"{record.name}/{episode.task}/episode_{episode.episode}: {episode.status}, left out")
                continue
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                episodes.append(episode_signals(record, episode, condition, preflight))
    return episodes, records, notes


def window_mean(values: np.ndarray, window: int) -> np.ndarray:
    """(steps,) -> the nan-mean over the last `window` steps up to each step (known up to t); nan where none."""
    values = np.asarray(values, np.float64)
    finite = np.isfinite(values)
    total = np.concatenate([[0.0], np.cumsum(np.where(finite, values, 0.0))])
    count = np.concatenate([[0], np.cumsum(finite)])
    end = np.arange(1, len(values) + 1)
    start = np.maximum(end - int(window), 0)
    n = count[end] - count[start]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (total[end] - total[start]) / np.where(n > 0, n, 1), math.nan)

"""Comparison of two runs on the same seeds: paired outcome verdicts, first-step drift and the IDENTICAL check.

`compare_runs(baseline_dir, candidate_dir, config)` reads both run folders (harness.analysis.runs), refuses
protocols that differ in what changes outcomes (`IncompatibleRuns`, one line naming the fields), pairs
finished episodes by (task, seed) and returns one `CompareResult` (harness.analysis.compare_result: what
compare.json holds, read by attribute; `to_json()` writes it):

- outcomes: per task and pooled, both success rates with Wilson intervals, the paired difference
  (candidate - baseline) with Newcombe's interval, the exact McNemar p-value, Holm's adjustment over the
  family {every task, pooled (when there are several tasks)}, a verdict (harness.analysis.paired) and the
  number of pairs the current rates would need to decide an UNDERPOWERED verdict;
- drift: at step 0 both arms saw the identical observation (same seed), so the difference of the step-0
  action chunks, the Jensen-Shannon divergence of the step-0 readout attention per layer and head and the
  change of target lift measure the model change alone, when the model is all that differs (`what_differs`:
  an intervention or another policy setting that differs is named, as what the drift measures); the same per step over the first k steps; and over
  whole episodes, marked confounded (trajectories diverge once actions differ);
- identical: every array of every pair (actions.npz, attention.npz) equal within `atol`, with the same
  outcomes: the overall verdict is then IDENTICAL. A run of a policy without attention (its attention.npz holds step
  and phase only, harness.outputs.writers) is compared on the arrays both runs have: against a run with attention,
  the attention arrays are left out of the check (so one deterministic policy, with and without attention, comes out
  IDENTICAL on identical actions) and one line says so, "attention only in the baseline" among the measures only one
  run took (`one_side_measures`); two runs without attention say so in one line too. No attention drift then.

Outcomes: n is the pairs in which both arms ran to an outcome (as in the run store's statistics); a pair in
which either arm errored (status "failed") is left out of the table and counted beside n ("errored pairs").
A task whose pairs are all identical shows IDENTICAL; the overall verdict is IDENTICAL if every pair is, else
the worst verdict of the tasks and the pooled table (harness.verdicts.GateVerdict's rank: ERRORED > REGRESSED >
SUSPECT > UNDERPOWERED > HELD > IMPROVED), so no task's verdict is hidden by a pooled one. A candidate that lacks
finished episodes the baseline has (a task it did not run, jobs it did not finish) is INCOMPLETE whatever its
pairs say, unless they already say ERRORED or REGRESSED: a gate cannot be passed by leaving work out. `exit_code`
maps the verdict to 0 (pass), 1 (REGRESSED or SUSPECT, or what --fail-on adds), 3 (ERRORED), 4 (INCOMPLETE,
whatever --fail-on); 2 is invalid input or outputs that could not be written (the CLI). The outcome tables and
their verdicts are harness.analysis.outcomes'; the verdicts' order and exit codes harness.verdicts'.
A committed baseline keeps only step-0 arrays (BASELINE.json says so): arrays are then compared over the
steps both arms stored.
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from harness.bounded import read_json
from harness.analysis.compare_result import (
    FORMAT,
    Arm,
    CompareConfig,
    CompareResult,
    DerivedMeasures,
    DifferingField,
    Differs,
    Drift,
    DriftBlock,
    GridInfo,
    IdenticalCheck,
    MissingPairs,
    OneSideMeasures,
    PairDetail,
    Provenance,
    RobustnessGrid,
    Step0Drift,
    StepDrift,
    WholeEpisodeDrift,
)
from harness.measures.attention import DERIVED_PREFIXES
from harness.analysis.equivalence import attention_divergence
from harness.analysis.protocol_fields import (ATTENTION_NOTES, attention_sides, incompatible_fields, one_side_line,
                                             one_side_measures, shared_arrays, what_differs, with_attention_sides)
from harness.analysis.outcomes import incompleteness, outcome_tables, outcome_verdicts, overall_verdict
from harness.analysis.provenance import input_agreement, provenance
from harness.analysis.runs import EpisodeRecord, RunRecord, load_run, read_npz
from harness.results import ABSENT
from harness.verdicts import DEFAULT_FAIL_ON, GateVerdict, gate_exit_code

BASELINE_MARKER = "BASELINE.json"  # written by scripts/make_baseline.py into a committed baseline
ARRAY_FILES = ("actions.npz", "attention.npz")


class IncompatibleRuns(ValueError):
    """The two runs cannot be paired (one line naming the fields or the problem)."""


# ------------------------------------------------------------------------------------------- pure maths

def action_difference(base: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """predicted chunks (..., horizon, dim) x2 -> (...) L2 norm of the difference over the whole chunk."""
    diff = np.asarray(cand, np.float64) - np.asarray(base, np.float64)
    return np.sqrt((diff ** 2).sum(axis=(-2, -1)))


def target_lift(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """attention.npz arrays -> {obs key: (steps, layers) target mass / target area} (1 = chance)."""
    out = {}
    for name, mass in arrays.items():
        if name.startswith("metrics/mask_mass/") and name.endswith("/target"):
            obs = name[len("metrics/mask_mass/"):-len("/target")]
            area = arrays.get(f"metrics/mask_area/{obs}/target")
            if area is not None:
                area = np.asarray(area, np.float64).reshape(-1, 1)
                out[obs] = np.divide(np.asarray(mass, np.float64), area, out=np.full(mass.shape, np.nan), where=area > 0)
    return out


# ------------------------------------------------------------------------------------------- reading

def _protocol(run: RunRecord) -> dict:
    manifest = run.manifest
    if isinstance(manifest.get("protocol"), dict):
        return manifest["protocol"]
    return {k: v for k, v in manifest.items() if k not in ("jobs", "run", "created", "format")}  # legacy


def _truncated(run: RunRecord) -> bool:
    """A committed baseline that keeps only the first steps' arrays."""
    return (run.path / BASELINE_MARKER).is_file()


def _load_arrays(episode: EpisodeRecord) -> dict[str, np.ndarray] | None:
    """Both array files of an episode, keys prefixed "actions.npz:" / "attention.npz:"; None when absent."""
    out = {}
    for name in ARRAY_FILES:
        path = episode.directory / name
        if not path.is_file():
            return None
        out.update({f"{name}:{key}": value for key, value in read_npz(path).items()})
    return out


def pair_episodes(baseline: RunRecord, candidate: RunRecord):
    """Finished episodes paired by (task, seed) -> (pairs [(task, seed, base, cand)], missing {arm: [[task, seed]]})."""
    def index(run):
        return {(e.task, e.seed if e.seed is not None else e.episode): e for e in run.episodes}

    base, cand = index(baseline), index(candidate)
    order = [key for key in base if key in cand]
    pairs = [(task, seed, base[(task, seed)], cand[(task, seed)]) for task, seed in order]
    missing = {
        "candidate": [[t, s] for (t, s) in base if (t, s) not in cand],  # run by the baseline only
        "baseline": [[t, s] for (t, s) in cand if (t, s) not in base],
    }
    return pairs, missing


# ------------------------------------------------------------------------------------------- per pair

def _step_count(arrays: dict[str, np.ndarray]) -> int:
    return int(arrays["attention.npz:step"].shape[0]) if "attention.npz:step" in arrays else 0


def _derived(key: str) -> bool:
    """An attention.npz array derived from the policy's outputs and the masks (MEASURES_VERSION covers it)."""
    return key.startswith(tuple(f"attention.npz:{prefix}" for prefix in DERIVED_PREFIXES))


def _first_difference(a: dict, b: dict, steps: int, atol: float, derived: bool | None = None) -> str | None:
    """None when every array agrees within atol over the first `steps` stored steps, else what differs first.
    derived: None compares every array, False only the policy's own (actions, attention, tokens), True only the
    derived measures."""
    if derived is not None:
        a = {k: v for k, v in a.items() if _derived(k) == derived}
        b = {k: v for k, v in b.items() if _derived(k) == derived}
    if set(a) != set(b):
        return f"array files hold different arrays: {sorted(set(a) ^ set(b))[:4]}"
    for key in sorted(a):
        x, y = a[key], b[key]
        stepwise = not key.startswith("attention.npz:tokens/") and x.ndim > 0
        if stepwise:
            x, y = x[:steps], y[:steps]
        if x.shape != y.shape:
            return f"{key} shape {x.shape} vs {y.shape}"
        if x.dtype.kind not in "fc" or y.dtype.kind not in "fc":  # ints, bools, strings: exact
            if not np.array_equal(x, y):
                return f"{key} differs"
            continue
        xf, yf = x.astype(np.float64), y.astype(np.float64)
        if not np.array_equal(np.isnan(xf), np.isnan(yf)):
            return f"{key} differs in NaN positions"
        diff = np.abs(np.nan_to_num(xf) - np.nan_to_num(yf))
        if diff.size and diff.max() > atol:
            return f"{key} max |diff| {diff.max():.3g}"
    return None


def _compare_pair(task, seed, base: EpisodeRecord, cand: EpisodeRecord, truncated: tuple[bool, bool],
                  config: CompareConfig, measures_changed: bool = False) -> dict:
    """One pair: outcome, IDENTICAL check and drift arrays (kept as numpy for aggregation). measures_changed: the
    runs were written under different definitions of the derived measures (MEASURES_VERSION), so a difference
    confined to them leaves the pair identical and is recorded as `derived_difference`."""
    out = {"task": task, "seed": seed, "baseline_dir": str(base.directory), "candidate_dir": str(cand.directory),
           "baseline_success": base.success, "candidate_success": cand.success,
           "baseline_steps": base.steps, "candidate_steps": cand.steps,
           "baseline_status": base.status, "candidate_status": cand.status}
    a = _load_arrays(base) if base.ok else None
    b = _load_arrays(cand) if cand.ok else None
    if a is None or b is None:  # an errored pair is never identical (and not an outcome pair: see outcome_tables)
        errored = [arm for arm, e in (("baseline", base), ("candidate", cand)) if not e.ok]
        out["identical"] = False
        out["difference"] = (f"the {' and '.join(errored)} episode errored (no outcome)" if errored
                             else "an episode has no arrays")
        return out
    sides = attention_sides(a, b)
    if sides != "both":
        out["attention_note"] = ATTENTION_NOTES[sides]
        a, b = shared_arrays(a, b)
    stored_a, stored_b = _step_count(a), _step_count(b)
    complete = (stored_a == base.steps or truncated[0]) and (stored_b == cand.steps or truncated[1])
    steps = min(stored_a, stored_b)
    difference = None
    if (base.success, base.steps, base.status) != (cand.success, cand.steps, cand.status):
        difference = f"outcome differs (success {base.success} -> {cand.success}, steps {base.steps} -> {cand.steps})"
    elif not complete:
        difference = "stored arrays are shorter than the episode"
    elif measures_changed:
        difference = _first_difference(a, b, steps, config.atol, derived=False)
        if difference is None:
            out["derived_difference"] = _first_difference(a, b, steps, config.atol, derived=True)
    else:
        difference = _first_difference(a, b, steps, config.atol)
    out["identical"] = difference is None
    out["difference"] = difference
    out["compared_steps"] = steps
    out["inputs"] = input_agreement(a, b)  # leading steps both arms fed the policy identical inputs

    pa, pb = a.get("actions.npz:predicted"), b.get("actions.npz:predicted")
    ra, rb = a.get("attention.npz:readout_attention"), b.get("attention.npz:readout_attention")
    if pa is not None and pb is not None and pa.shape[1:] == pb.shape[1:] and steps:
        out["action_l2"] = action_difference(pa[:steps], pb[:steps])  # (steps,)
        out["action_max_abs_step0"] = float(np.abs(pb[0].astype(np.float64) - pa[0]).max())
    tokens_equal = all(
        np.array_equal(a[k], b.get(k)) for k in a if k.startswith("attention.npz:tokens/")
    ) and ra is not None and rb is not None and ra.shape[1:] == rb.shape[1:]
    if tokens_equal and steps:
        out["js"] = attention_divergence(ra[:steps], rb[:steps])  # (steps, layers, heads)
        out["js_step0_max"] = float(out["js"][0].max())
        la = target_lift({k.split(":", 1)[1]: v for k, v in a.items() if k.startswith("attention.npz:")})
        lb = target_lift({k.split(":", 1)[1]: v for k, v in b.items() if k.startswith("attention.npz:")})
        out["lift_change_step0"] = {obs: lb[obs][0] - la[obs][0] for obs in la if obs in lb}  # (layers,)
    elif not tokens_equal and sides == "both":
        out["attention_note"] = "token maps or attention shapes differ (different architecture): no attention drift"
    return out


# ------------------------------------------------------------------------------------------- aggregation

def _mean(values: list[np.ndarray]):
    return np.mean(np.stack(values), axis=0) if values else None


def _drift(pairs: list[dict], config: CompareConfig) -> Drift:
    def step0(group: list[dict]) -> DriftBlock:
        js = [p["js"][0] for p in group if "js" in p]
        actions = [p["action_l2"][0] for p in group if "action_l2" in p]
        lift: dict[str, list] = {}
        for p in group:
            for obs, change in p.get("lift_change_step0", {}).items():
                lift.setdefault(obs, []).append(change)
        js_mean = _mean(js)  # (layers, heads)
        return DriftBlock(
            pairs=len(group),
            action_l2=float(np.mean(actions)) if actions else None,
            action_max_abs=max((p["action_max_abs_step0"] for p in group if "action_max_abs_step0" in p), default=None),
            js_layer_head=js_mean,
            js_layer=None if js_mean is None else js_mean.mean(axis=-1),
            js_mean=None if js_mean is None else float(js_mean.mean()),
            target_lift_change={obs: np.nanmean(np.stack(v), axis=0) for obs, v in lift.items()},
        )

    tasks = {}
    for p in pairs:
        tasks.setdefault(p["task"], []).append(p)
    first = []
    for t in range(config.first_steps):
        js = [p["js"][t].mean() for p in pairs if "js" in p and p["js"].shape[0] > t]
        actions = [p["action_l2"][t] for p in pairs if "action_l2" in p and p["action_l2"].shape[0] > t]
        if not js and not actions:
            break
        first.append(StepDrift(step=t, pairs=max(len(js), len(actions)),
                               action_l2=float(np.mean(actions)) if actions else None,
                               js_mean=float(np.mean(js)) if js else None))
    whole_js = [float(p["js"].mean()) for p in pairs if "js" in p]
    whole_actions = [float(p["action_l2"].mean()) for p in pairs if "action_l2" in p]
    return Drift(
        step0=Step0Drift(tasks={task: step0(group) for task, group in tasks.items()}, overall=step0(pairs)),
        first_steps=tuple(first),
        whole_episode=WholeEpisodeDrift(
            confounded=True,
            note="after step 0 the arms see different observations once their actions differ; "
                 "only step 0 isolates the model",
            action_l2=float(np.mean(whole_actions)) if whole_actions else None,
            js_mean=float(np.mean(whole_js)) if whole_js else None,
            pairs=len(whole_js),
        ),
    )


def _arm(run: RunRecord) -> Arm:
    return Arm(run=run.name, path=str(run.path), model=run.model.source, random_weights=run.model.is_random,
               status=run.status, episodes=len(run.episodes), missing_jobs=run.missing,
               errors=sum(not e.ok for e in run.episodes), git_commit=run.git_commit,
               unverified=run.unverified,  # finished episodes whose rows record no file digests (older runs)
               arrays="first steps only (committed baseline)" if _truncated(run) else "all steps")


def measures_versions(baseline: RunRecord, candidate: RunRecord) -> tuple:
    """Each run's manifest "measures_version" (None for runs written before it was recorded)."""
    return tuple(run.manifest.get("measures_version") for run in (baseline, candidate))


def _derived_block(baseline: RunRecord, candidate: RunRecord, details: list[dict]) -> DerivedMeasures | None:
    """Identical trajectories whose derived measures differ because their definition changed, or None."""
    differing = [d for d in details if d["identical"] and d.get("derived_difference")]
    if not differing:
        return None
    versions = measures_versions(baseline, candidate)
    shown = ["unrecorded" if v is None else str(v) for v in versions]
    first = f"{differing[0]['task']} seed {differing[0]['seed']}: {differing[0]['derived_difference']}"
    return DerivedMeasures(
        baseline_version=versions[0], candidate_version=versions[1], pairs=len(differing), first_difference=first,
        note=f"the policy's trajectories are identical (actions, attention); only derived measures differ, "
             f"because their definition changed (measures version {shown[0]} -> {shown[1]}); first: {first}")


def compare_runs(baseline_dir: str | Path, candidate_dir: str | Path, config: CompareConfig = CompareConfig(),
                 require_complete: bool = True) -> CompareResult:
    """Compare two run folders (see the module docstring). Raises IncompatibleRuns / NotARunError (exit 2).

    require_complete=False: a candidate lacking the baseline's episodes is compared on the pairs it has (regress,
    whose sequential test may stop early, decides incompleteness itself)."""
    baseline, candidate = load_run(baseline_dir, legacy=False), load_run(candidate_dir, legacy=False)
    fields = incompatible_fields(_protocol(baseline), _protocol(candidate))
    if fields:
        raise IncompatibleRuns(f"the runs' protocols differ in fields that change outcomes: {', '.join(fields)}; "
                               "re-run the candidate with the baseline's settings (or use `octo-harness regress`)")
    differs = what_differs(_protocol(baseline), _protocol(candidate))
    pairs, missing = pair_episodes(baseline, candidate)
    if not pairs:
        raise IncompatibleRuns(f"no (task, seed) pair is finished in both {baseline.path} and {candidate.path}; "
                               "run the candidate on the baseline's tasks and seeds")
    truncated = (_truncated(baseline), _truncated(candidate))
    before, after = measures_versions(baseline, candidate)
    details = [_compare_pair(task, seed, b, c, truncated, config, before != after) for task, seed, b, c in pairs]
    return _result(baseline, candidate, details, missing, truncated, config, differs, require_complete)


def _result(baseline: RunRecord, candidate: RunRecord, details: list[dict], missing: dict, truncated: tuple,
            config: CompareConfig, differs: dict, require_complete: bool = True) -> CompareResult:
    """The comparison of paired episode details (`task` names the Holm family's cells); `differs`: what differs
    between the protocols (`what_differs`); require_complete: as in `compare_runs`."""
    tables, errored = outcome_tables(details)
    outcomes = outcome_verdicts(tables, config, errored)
    identical = all(d["identical"] for d in details) and not missing["baseline"] and not missing["candidate"]
    first_diff = next((f"{d['task']} seed {d['seed']}: {d['difference']}" for d in details if not d["identical"]),
                      "pairs are missing from one run" if not identical else None)
    missing_tasks = {t for t, _ in missing["baseline"] + missing["candidate"]}
    tasks = {}
    for task, block in outcomes.tasks.items():  # a task whose every pair is identical says so in its row
        same = task not in missing_tasks and all(d["identical"] for d in details if d["task"] == task)
        tasks[task] = replace(block, paired_verdict=block.verdict,
                              verdict=GateVerdict.IDENTICAL if same else block.verdict)
    overall = replace(outcomes.overall, paired_verdict=outcomes.overall.verdict,
                      verdict=GateVerdict.IDENTICAL if identical else outcomes.overall.verdict)
    notes = [note for block in [*tasks.values(), overall]
             if block.verdict != GateVerdict.IDENTICAL for note in block.notes]  # nothing to explain there
    outcomes = replace(outcomes, tasks=tasks, overall=overall)
    verdict = overall_verdict(outcomes, identical)
    incomplete = incompleteness(missing["candidate"], baseline.path, candidate.path)
    if require_complete and incomplete is not None:
        notes.insert(0, incomplete.note)
        verdict = GateVerdict.worst([verdict, GateVerdict.INCOMPLETE])  # ERRORED and REGRESSED stand
    protocol = _protocol(baseline)
    one_side, attention_note = with_attention_sides(one_side_measures(protocol, _protocol(candidate)), details)
    one_side_note = one_side_line(one_side)
    notes += [note for note in (one_side_note, attention_note) if note]
    return CompareResult(
        format=FORMAT,
        verdict=verdict,
        config=config,
        baseline=_arm(baseline),
        candidate=_arm(candidate),
        env=protocol.get("env") if isinstance(protocol.get("env"), dict) else None,
        perturb=protocol.get("perturb") if isinstance(protocol.get("perturb"), str) else None,
        pairs=len(details),
        missing_pairs=MissingPairs(candidate=tuple(map(tuple, missing["candidate"])),
                                   baseline=tuple(map(tuple, missing["baseline"]))),
        incomplete=incomplete,
        identical=IdenticalCheck(
            identical=identical,
            pairs_identical=sum(d["identical"] for d in details),
            first_difference=first_diff if not identical else None,
            atol=config.atol,
            steps_compared="first stored steps of the committed baseline" if any(truncated) else "all steps",
            derived_measures=_derived_block(baseline, candidate, details),
        ),
        outcomes=replace(outcomes, notes=tuple(notes)),
        drift=_drift(details, config),
        differs=Differs(model=differs["model"], other=tuple(DifferingField(**o) for o in differs["other"]),
                        cause=differs["cause"], drift_label=differs["drift_label"]),
        provenance=Provenance(**provenance(baseline.manifest, candidate.manifest, details, differs=differs)),
        pair_details=tuple(_pair_detail(d) for d in details),
        one_side_measures=OneSideMeasures(**one_side) if one_side_note else ABSENT,
    )


def _pair_detail(d: dict) -> PairDetail:
    """A pair's details without its arrays (their step-0 values kept)."""
    return PairDetail(**{k: v for k, v in d.items() if k not in ("js", "action_l2", "lift_change_step0")},
                      step0_action_l2=float(d["action_l2"][0]) if "action_l2" in d else None,
                      step0_js_mean=float(d["js"][0].mean()) if "js" in d else None)


GRID_FILE = "robustness.json"  # harness.gate.robustness writes it into a grid folder


def is_grid(path: str | Path) -> bool:
    """Whether `path` is a robustness grid folder (`octo-harness robustness`) rather than one run."""
    return (Path(path) / GRID_FILE).is_file()


def read_grid(path: str | Path) -> RobustnessGrid:
    """robustness.json of a grid folder (runs: {run name: perturb or None}, ...); one line if unreadable."""
    path = Path(path) / GRID_FILE
    try:
        grid = read_json(path)
    except (OSError, ValueError) as exc:
        raise IncompatibleRuns(f"{path}: unreadable robustness grid ({exc}); re-create it with octo-harness robustness")
    runs = grid.get("runs") if isinstance(grid, dict) else None
    if not isinstance(runs, dict) or not runs or not all(isinstance(k, str) and "/" not in k and k not in ("", ".", "..")
                                                       for k in runs):
        raise IncompatibleRuns(f"{path}: 'runs' must map run folder names to perturbations; re-create the grid")
    try:
        return RobustnessGrid.from_json(grid)
    except (TypeError, ValueError) as exc:
        raise IncompatibleRuns(f"{path}: not a robustness grid ({exc}); re-create it with octo-harness robustness")


def compare_grids(baseline_dir: str | Path, candidate_dir: str | Path, config: CompareConfig = CompareConfig(),
                  require_complete: bool = True) -> CompareResult:
    """Two robustness grids, condition by condition: every (task, condition) is one cell of the Holm family (plus
    the pooled table), at the same family-wise alpha as a task of `compare_runs`: a candidate that holds its nominal
    success but loses one condition by more than max_drop is REGRESSED or SUSPECT there when the test or the interval
    shows the loss, else UNDERPOWERED. Every condition of the baseline grid must be in the candidate's (one line
    otherwise)."""
    base_grid, cand_grid = read_grid(baseline_dir), read_grid(candidate_dir)
    absent = [name for name in base_grid.runs if name not in cand_grid.runs]
    if absent:
        raise IncompatibleRuns(f"the candidate grid {candidate_dir} lacks condition(s) {', '.join(absent)} of the "
                               "baseline grid; run octo-harness robustness with the baseline's --perturb and --levels")
    details, missing, arms, truncated = [], {"baseline": [], "candidate": []}, None, (False, False)
    for name, perturb in base_grid.runs.items():
        baseline, candidate = load_run(Path(baseline_dir) / name, legacy=False), load_run(Path(candidate_dir) / name, legacy=False)
        fields = incompatible_fields(_protocol(baseline), _protocol(candidate))
        if fields:
            raise IncompatibleRuns(f"condition {name}: the runs' protocols differ in fields that change outcomes: "
                                   f"{', '.join(fields)}; re-run the candidate grid with the baseline's settings")
        if (_protocol(baseline).get("perturb") or None) != (perturb or None):
            raise IncompatibleRuns(f"condition {name}: {baseline.path} holds perturb "
                                   f"{_protocol(baseline).get('perturb')!r}, the grid file says {perturb!r}")
        pairs, miss = pair_episodes(baseline, candidate)
        arms = arms or (baseline, candidate)
        cond_truncated = (_truncated(baseline), _truncated(candidate))
        truncated = (truncated[0] or cond_truncated[0], truncated[1] or cond_truncated[1])
        for task, seed, b, c in pairs:
            before, after = measures_versions(baseline, candidate)
            d = _compare_pair(task, seed, b, c, cond_truncated, config, before != after)
            details.append({**d, "task": f"{task} / {name}", "condition": name})
        for side in ("baseline", "candidate"):
            missing[side] += [[f"{t} / {name}", s] for t, s in miss[side]]
    if not details:
        raise IncompatibleRuns(f"no (task, seed) pair is finished in both grids {baseline_dir} and {candidate_dir}")
    result = _result(arms[0], arms[1], details, missing, truncated, config,
                     what_differs(_protocol(arms[0]), _protocol(arms[1])), require_complete)
    return replace(result, grid=GridInfo(baseline=str(Path(baseline_dir).resolve()),
                                         candidate=str(Path(candidate_dir).resolve()),
                                         conditions=tuple(base_grid.runs), cells=len(result.outcomes.tasks),
                                         perturb=dict(base_grid.runs)))


def exit_code(result: CompareResult, fail_on: str = DEFAULT_FAIL_ON) -> int:
    """0 pass, 1 regression (REGRESSED, SUSPECT, or what --fail-on adds), 3 ERRORED, 4 INCOMPLETE
    (harness.verdicts.gate_exit_code)."""
    return gate_exit_code(result.verdict, fail_on)

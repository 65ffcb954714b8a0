"""Pre-flight: before the first episode, is the harness feeding the checkpoint what it was trained on?

Two checks, each on the checkpoint's own evidence, never on its conventions file (harness.toml):

- image convention, per camera: the first frame of the run's first task, as the harness feeds it, against the
  checkpoint's example frame of that camera (example_batch.msgpack: a finetune's real training frame) under each
  image convention (harness.measures.orientation);
- action space: the action statistics of the run's dataset key (dataset_statistics.json) against the ranges the
  chosen action space expects (translation scale, gripper range).

Each check gives a verdict: "consistent", "MISMATCH" (naming the flag that fits) or "inconclusive" (saying why).
`--preflight warn` (the default) prints one line per finding that is not consistent; `strict` also refuses a
MISMATCH (exit 2, before the first episode); `off` skips both checks. The manifest records the findings
("preflight", outside the protocol and its hash). docs/environments.md explains the thresholds below and where they
were measured.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from envs.options import ACTION_SPACE_UNITS, IMAGE_CONVENTIONS, to_convention
from harness.measures.orientation import MEASURE, is_flat, orientation_scores
from harness.options import option
from harness.verdicts import PreflightVerdict

log = logging.getLogger(__name__)

MODES = ("warn", "strict", "off")
# Thresholds on the measure's scores (Pearson correlations), from the margins the reference checkpoints give over
# every task they run (scripts/preflight_margins.py; the model cards hold the tables). Right orientation's score:
# 0.40 at least (LIBERO's wrist view); another robosuite scene (PickPlaceCan against Stack) under 0.1. Vertical
# margins: 0.56 at least. Mirror margins: LIBERO-Object's agentview 0.13 to 0.20, its wrist view -0.05 to 0.07,
# robosuite's views -0.01 to 0.01 (the wrong side never ahead by more than 0.051).
MIN_SCORE = 0.3  # the best orientation scores less: another scene or camera, inconclusive
VERTICAL_MARGIN = 0.25  # a vertically flipped orientation beats (or loses to) the fed one by this much: decided
MIRROR_MARGIN = 0.1  # the same for a left-right mirror (upright <-> rot180): twice the wrong side's largest lead
# Action statistics: the largest |p01|, |p99| of the three translation values, and the gripper's range
METRES_AT_MOST = 0.1  # end-effector deltas in metres per step (octo-delta, Bridge: about 0.01)
OSC_AT_LEAST = 0.2  # controller inputs in [-1, 1] (robosuite, libero) reach far beyond
EXPECTED = ACTION_SPACE_UNITS  # each action space's (translation, gripper range), envs.options
CONSISTENT, MISMATCH, INCONCLUSIVE = (PreflightVerdict.CONSISTENT, PreflightVerdict.MISMATCH,
                                     PreflightVerdict.INCONCLUSIVE)  # a check's verdict (harness.verdicts)


class PreflightMismatch(ValueError):
    """--preflight strict and a check found a MISMATCH (the message: its lines)."""


@dataclass(frozen=True)
class PreflightOptions:
    """Whether and how the pre-flight checks run: recorded in the manifest ("preflight"), outside the protocol and
    its hash (they change no episode)."""

    mode: str = option(
        "warn", "--preflight", "check the frames and action space fed to the checkpoint against its example batch and "
        "statistics before the first episode: warn, strict (a MISMATCH exits 2) or off", file=(str,),
        choices=MODES, hashed=False, field="mode",
        doc="before the first episode, compare the first frame of each camera with the checkpoint's example frame "
            "under each image convention, and the action statistics with the action space "
            "([environments.md](environments.md#is-the-harness-feeding-the-model-what-it-was-trained-on)); `warn` "
            "prints one line per finding, `strict` also exits 2 on a MISMATCH, `off` skips it [warn]")

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"--preflight {self.mode!r}: use one of {', '.join(MODES)}")


def _relation(a: str, b: str) -> str:
    """"mirror" when two conventions differ by a left-right mirror only (upright, rot180), else "vertical"."""
    return "mirror" if {a, b} == {"upright", "rot180"} else "vertical"


def image_finding(key: str, example: np.ndarray, fed: np.ndarray, convention: str, default: str | None = None,
                  datasets: int = 1) -> dict:
    """The verdict for one camera: `example` (H, W, 3) the checkpoint's example frame, `fed` (h, w, 3) the frame the
    run feeds in `convention`; `default` the task family's own convention (its suite's, envs.suites.Suite.defaults), which
    decides where only a mirror is in doubt and the scene cannot show it: the fed one is consistent when it is the
    family's, else inconclusive. `datasets`: how many datasets the checkpoint's statistics hold (a pretrained
    mixture's example frame shows one of them: another scene). {verdict, fed, best, scores, margin, suggest, line}
    (line: "" when nothing to say)."""
    base = {"check": f"image:{key}", "fed": convention}
    if datasets > 1:
        return {**base, "verdict": INCONCLUSIVE, "reason": "multi-dataset checkpoint",
                "line": f"{key}: {INCONCLUSIVE}: the checkpoint was trained on {datasets} datasets, so its example "
                        "frame may show another scene; finetune-specific frames are needed to check the orientation"}
    if is_flat(example):
        return {**base, "verdict": INCONCLUSIVE, "reason": "blank example frame",
                "line": f"{key}: {INCONCLUSIVE}: the checkpoint's example frame is blank (all zeros or one colour), "
                        "so its orientation cannot be checked"}
    scores = orientation_scores(example, to_convention(fed, convention))
    ranked = sorted(IMAGE_CONVENTIONS, key=lambda c: -scores[c])
    best = ranked[0]
    out = {**base, "measure": MEASURE, "scores": {c: round(scores[c], 4) for c in IMAGE_CONVENTIONS}, "best": best,
           "margin": round(scores[best] - scores[ranked[1]], 4)}
    shown = f"{best} {scores[best]:.2f}, fed {convention} {scores[convention]:.2f}"
    if scores[best] < MIN_SCORE:
        return {**out, "verdict": INCONCLUSIVE, "reason": "another scene or camera",
                "line": f"{key}: {INCONCLUSIVE}: the example frame matches no orientation well (best {shown}; under "
                        f"{MIN_SCORE}): another scene or camera"}
    gap = {c: scores[c] - scores[convention] for c in IMAGE_CONVENTIONS if c != convention}
    need = {c: VERTICAL_MARGIN if _relation(c, convention) == "vertical" else MIRROR_MARGIN for c in gap}
    beating = [c for c in ranked if c in gap and gap[c] >= need[c]]
    if beating:
        tied = [c for c in beating if c == beating[0] or scores[beating[0]] - scores[c] < (
            VERTICAL_MARGIN if _relation(c, beating[0]) == "vertical" else MIRROR_MARGIN)]
        named = sorted(tied, key=lambda c: c != default)  # the family's own first where a mirror ties
        flags = " or ".join(f"--image-convention {c}" for c in named)
        return {**out, "verdict": MISMATCH, "suggest": named,
                "line": f"{key}: {MISMATCH}: the frames fed as {convention} match the checkpoint's example frame "
                        f"better as {' or '.join(named)} ({shown}); run with {flags}"}
    unclear = [c for c in gap if gap[c] > -need[c]]  # not beaten by the margin
    vertical = [c for c in unclear if _relation(c, convention) == "vertical"]
    if vertical:
        return {**out, "verdict": INCONCLUSIVE, "reason": "margin below threshold",
                "line": f"{key}: {INCONCLUSIVE}: fed {convention} and {' and '.join(vertical)} score within "
                        f"{VERTICAL_MARGIN} ({shown})"}
    if unclear and convention != default:  # a mirror the scene cannot show, and not the family's own convention
        return {**out, "verdict": INCONCLUSIVE, "reason": "mirror-only difference",
                "line": f"{key}: {INCONCLUSIVE}: mirror-only difference not measurable here (fed {convention}, its "
                        f"mirror {unclear[0]} within {MIRROR_MARGIN}: {gap[unclear[0]]:+.2f})"}
    return {**out, "verdict": CONSISTENT, **({"mirror": "not measurable"} if unclear else {}), "line": ""}


def _extent(stats: dict, lo: str, hi: str, dims: slice) -> tuple[float, float] | None:
    low, high = stats.get(lo, stats.get("min")), stats.get(hi, stats.get("max"))
    if low is None or high is None:
        return None
    return float(np.min(np.asarray(low, np.float64)[dims])), float(np.max(np.asarray(high, np.float64)[dims]))


def action_classes(stats: dict, gripper: bool = True) -> dict:
    """{translation: "metres" | "controller" | None, gripper: "0..1" | "-1..1" | None, ...} from one dataset's action
    statistics (p01/p99, else min/max); None where the statistics cannot tell."""
    dims = len(np.asarray(stats.get("mean", stats.get("max", [])), np.float64).ravel())
    found: dict = {"dims": dims}
    moves = _extent(stats, "p01", "p99", slice(0, 3)) if dims >= 3 else None
    if moves is not None:
        reach = max(abs(moves[0]), abs(moves[1]))
        found["translation_reach"] = round(reach, 4)
        found["translation"] = "metres" if reach <= METRES_AT_MOST else (
            "controller" if OSC_AT_LEAST <= reach <= 1.0 + 1e-3 else None)
    if gripper and dims >= 7:
        low, high = _extent(stats, "min", "max", slice(6, 7)) or (float("nan"), float("nan"))
        found["gripper_range"] = [round(low, 4), round(high, 4)]
        if low <= -0.5 and high <= 1.0 + 1e-3:
            found["gripper"] = "-1..1"
        elif low >= -1e-3 and high <= 1.0 + 1e-3 and high - low >= 0.5:
            found["gripper"] = "0..1"
    return found


def action_finding(statistics: dict | None, dataset_key: str | None, action_space: str, hold_gripper=None) -> dict:
    """The verdict for the action space from `statistics` (dataset_statistics.json) under `dataset_key`."""
    stats = ((statistics or {}).get(dataset_key or "") or {}).get("action")
    if not isinstance(stats, dict):
        return {"check": "action", "fed": action_space, "verdict": INCONCLUSIVE, "reason": "no action statistics",
                "line": f"action: {INCONCLUSIVE}: dataset_statistics.json holds no action statistics for "
                        f"{dataset_key!r}"}
    return _verdict(action_classes(stats, gripper=hold_gripper is None), action_space, hold_gripper, "statistics",
                    "the checkpoint's action statistics")


def chunk_classes(chunk: np.ndarray, gripper: bool = True) -> dict:
    """What one returned action chunk (horizon, dims) tells, only where it decides: translation values beyond
    METRES_AT_MOST (up to 1) are controller inputs (small ones could be either: a slow first move), a gripper value
    at -0.5 or below is the -1..1 convention (values in 0..1 could be either)."""
    chunk = np.asarray(chunk, np.float64).reshape(-1, np.shape(chunk)[-1])
    found: dict = {"dims": int(chunk.shape[-1])}
    if chunk.shape[-1] >= 3:
        reach = float(np.max(np.abs(chunk[:, :3])))
        found["translation_reach"] = round(reach, 4)
        if METRES_AT_MOST < reach <= 1.0 + 1e-3:
            found["translation"] = "controller"
    if gripper and chunk.shape[-1] >= 7:
        low, high = float(chunk[:, 6].min()), float(chunk[:, 6].max())
        found["gripper_range"] = [round(low, 4), round(high, 4)]
        if low <= -0.5 and high <= 1.0 + 1e-3:
            found["gripper"] = "-1..1"
    return found


def chunk_finding(chunk: np.ndarray, action_space: str, hold_gripper=None) -> dict:
    """The verdict for the action space from the first chunk a policy without action statistics returned (a policy
    behind a server): decisive only where one chunk decides (chunk_classes)."""
    return _verdict(chunk_classes(chunk, gripper=hold_gripper is None), action_space, hold_gripper, "first chunk",
                    "the policy's first action chunk")


def _verdict(found: dict, action_space: str, hold_gripper, evidence: str, said_by: str) -> dict:
    base = {"check": "action", "fed": action_space, "evidence": evidence} if evidence != "statistics" else {
        "check": "action", "fed": action_space}
    polarity = "the statistics cannot tell the gripper's polarity (which end is open)" if evidence == "statistics" \
        else "one chunk cannot tell the gripper's polarity (which end is open)"
    features = {"translation": 0} if hold_gripper is not None else {"translation": 0, "gripper": 1}
    known = {f: found.get(f) for f in features if found.get(f) is not None}
    fits = [s for s in EXPECTED if all(EXPECTED[s][features[f]] == v for f, v in known.items())]
    out = {**base, **found, "fits": fits, "note": polarity}
    said = ", ".join(f"{f} {v}" + (f" (reach {found['translation_reach']})" if f == "translation" else "")
                     for f, v in known.items())
    if known and action_space not in fits:
        suggest = f"; run with {' or '.join(f'--action-space {s}' for s in fits)}" if fits else ""
        want = ", ".join(f"{f} {EXPECTED[action_space][i]}" for f, i in features.items())
        return {**out, "verdict": MISMATCH, "suggest": fits,
                "line": f"action: {MISMATCH}: {said_by} say {said}; the {action_space} action "
                        f"space expects {want}{suggest}"}
    if len(known) < len(features):
        missing = ", ".join(f for f in features if f not in known)
        where = "the statistics do not" if evidence == "statistics" else "the first action chunk does not"
        return {**out, "verdict": INCONCLUSIVE, "reason": f"{missing} not told by the {evidence}",
                "line": f"action: {INCONCLUSIVE}: {where} tell the {missing} "
                        f"({said or 'nothing known'}); {polarity}"}
    return {**out, "verdict": CONSISTENT, "line": ""}


def first_chunk(model, config, env, seed: int) -> np.ndarray:
    """The action chunk `model` (a harness.policies.Policy) returns for the env's first observation after
    `reset(seed=seed)`, with the task's instruction (one inference, outside any episode)."""
    observation, info = env.reset(seed=seed)
    policy = model.closed_loop(config)
    policy.reset((info or {}).get("instruction", ""), seed=seed)
    return np.asarray(policy.step(observation).chunk)


def first_frames(env, seed: int) -> dict[str, np.ndarray]:
    """{image key: (h, w, 3) uint8} the env's first observation after `reset(seed=seed)`, as a run feeds it."""
    observation, _ = env.reset(seed=seed)
    return {k: np.asarray(v) for k, v in observation.items() if k.startswith("image_") and np.ndim(v) == 3}


def example_frames(model) -> dict[str, np.ndarray]:
    """{image key: (H, W, 3) uint8} the last frame of the checkpoint's example batch per camera."""
    observation = (getattr(model, "example_batch", None) or {}).get("observation", {})
    out = {}
    for key, value in observation.items():
        array = np.asarray(value)
        if key.startswith("image_") and array.ndim >= 3 and array.shape[-1] == 3:
            out[key] = array.reshape(-1, *array.shape[-3:])[-1]
    return out


def run_checks(model, env, seed: int, convention: str, action_space: str, dataset_key: str | None,
               hold_gripper=None, default: str | None = None, config=None) -> list[dict]:
    """Every finding for a run: one per camera the model and the env share, then the action space's (from the
    policy's action statistics; a policy without them, given `config`, from the first chunk it returns)."""
    examples = example_frames(model)
    frames = first_frames(env, seed)
    datasets = len(model.dataset_statistics or {})
    found = [image_finding(k, examples[k], frames[k], convention, default, datasets) for k in examples if k in frames]
    from_chunk = config is not None and model.preflight_from_chunk
    found += [_no_example(k, "the policy's metadata has no example frame") for k in frames
              if from_chunk and k not in examples and k in model.image_sizes]
    statistics = model.dataset_statistics
    if from_chunk and not statistics:
        found.append(chunk_finding(first_chunk(model, config, env, seed), action_space, hold_gripper))
    else:
        found.append(action_finding(statistics, dataset_key, action_space, hold_gripper))
    return found


def _no_example(key: str, why: str) -> dict:
    return {"check": f"image:{key}", "verdict": INCONCLUSIVE, "reason": why, "line": f"{key}: {INCONCLUSIVE}: {why}"}


def record(mode: str, findings: list[dict], task: str | None = None) -> dict:
    """The manifest's "preflight" block."""
    return {"mode": mode, **({"task": task} if task else {}),
            "findings": [{k: v for k, v in f.items() if k != "line"} for f in findings]}


def report(mode: str, findings: list[dict], has_conventions_file: bool = True) -> list[str]:
    """The console lines (one per finding that is not consistent); raises PreflightMismatch under strict."""
    lines = [f"preflight: {f['line']}" for f in findings if f["verdict"] != CONSISTENT or not has_conventions_file
             if f["line"]]
    if not has_conventions_file and all(f["verdict"] == CONSISTENT for f in findings):
        lines.append("preflight: the checkpoint has no harness.toml; frames and action statistics are consistent "
                     "with this run's conventions")
    if mode == "strict" and any(f["verdict"] == MISMATCH for f in findings):
        raise PreflightMismatch(" | ".join(lines) + " (--preflight strict; fix the convention or pass --preflight warn)")
    return lines


def summary(block: dict | None) -> str:
    """One line for the report's run manifest: each check's verdict."""
    if not block:
        return "not run (a run made before the pre-flight check)"
    if block.get("mode") == "off":
        return "off"
    parts = [f"{f['check']}: {f['verdict']}" + (f" (fits {' or '.join(f['suggest'])})" if f.get("suggest") else "")
             for f in block.get("findings", [])]
    return f"{block.get('mode')}: " + ("; ".join(parts) or "nothing to check")


def check_run(mode: str, protocol, model, env, seed: int, dataset_key: str | None) -> dict:
    """The checks of a run before its first episode, on `env` (the first task's, already made): the console lines
    (logged), PreflightMismatch under strict, and the manifest's block."""
    if mode == "off" or env is None:
        return {"mode": mode}
    from envs import suites
    from harness.conventions import CONVENTIONS_FILE

    task = protocol.tasks[0]
    options = protocol.env_for(task)
    findings = run_checks(model, env, seed, options.image_convention, options.action_space, dataset_key,
                          options.hold_gripper, suites.of(task).defaults["image_convention"], protocol.policy)
    folder = model.checkpoint_dir
    declared = model.preflight_from_chunk  # a served policy: its server or file declares conventions
    for line in report(mode, findings, declared or (folder is not None and (Path(folder) / CONVENTIONS_FILE).is_file())):
        log.warning("%s", line)
    return record(mode, findings, task)

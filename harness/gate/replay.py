"""`octo-harness replay RUN [--model X]`: a model open loop on exactly the inputs a run recorded, against what
the run recorded: the model change isolated from the simulator and the platform.

A run made with `--record-inputs` keeps, per episode, the newest history entry the policy was fed at every
step (inputs.npz: resized frames, raw proprio, in the env's image convention), the episode's seed and
instruction. Replay rebuilds every observation window from those entries (harness.policy.window_from_entries,
the function the closed loop uses), asks the model for the same step's chunk with the same rng key
(`step_key(seed, step)`), the run's policy settings and a batch-1 call, and compares chunk and readout
attention with actions.npz / attention.npz (harness.analysis.equivalence). Inferred steps only (a
receding-horizon step that reused a chunk has nothing to replay).

Verdict: EQUIVALENT (every step within the tolerances) or CHANGED (the first step beyond them, and how
far); exit 0 / 1; 2 for invalid input (a run without recorded inputs, a model whose inputs differ). The result is a
`ReplayResult` (harness.gate.results: replay.json, read by attribute; `to_json()` writes it).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from harness.gate.config import GateConfig
from harness.gate.results import REPLAY_FORMAT, ChangeAt, EpisodeReplay, FirstChange, ReplayResult
from harness.analysis.equivalence import Tolerances, action_change, action_scale, attention_change, first_change
from harness.analysis.runs import EpisodeRecord, load_run, read_npz
from harness.results import ABSENT
from harness.run.protocol import protocol_from_manifest
from harness.verdicts import ReplayVerdict

log = logging.getLogger(__name__)

FORMAT = REPLAY_FORMAT
INPUTS = "inputs.npz"


class ReplayInputError(ValueError):
    """The run cannot be replayed (one line naming the fix)."""


def recorded_inputs(episode: EpisodeRecord) -> dict[str, np.ndarray]:
    """inputs.npz of an episode as {name: array}; ReplayInputError when the run did not record inputs."""
    return read_npz(inputs_path(episode))


def inputs_path(episode: EpisodeRecord) -> Path:
    """The episode's inputs.npz; ReplayInputError when the run did not record inputs."""
    path = episode.directory / INPUTS
    if not path.is_file():
        raise ReplayInputError(f"{episode.directory} has no {INPUTS}; replay needs a run made with --record-inputs "
                               "(run the protocol again with that flag)")
    return path


def _recorded_outputs(episode: EpisodeRecord) -> tuple[np.ndarray, np.ndarray]:
    """(predicted chunks (steps, horizon, dims), readout attention (steps, layers, heads, readouts, keys)) as stored."""
    actions = read_npz(episode.directory / "actions.npz", "predicted")
    attention = read_npz(episode.directory / "attention.npz", "readout_attention")
    return actions["predicted"], attention["readout_attention"]


def no_attention_error(run) -> ReplayInputError:
    """Replay of a run whose policy gave no attention (a served one): one line naming what it needs."""
    return ReplayInputError(f"{run.path} was made by {run.model.source}, a policy without attention (a served one): "
                            "replay needs that policy's server and attention to compare with; start the server, run "
                            "the protocol again and compare the two runs with `octo-harness compare`")


def replay_episode(inference, episode: EpisodeRecord, window: int, goals, tolerances: Tolerances,
                   policy=None) -> EpisodeReplay:
    """One episode: replay its inferred steps with `policy`'s `inference` (the inference's own model where no policy
    is given); returns per-step changes and the episode's verdict."""
    from harness.policy import InferenceRequest, TaskPrompt, window_from_entries

    inputs = recorded_inputs(episode)
    keys = [k[len("input/"):] for k in inputs if k.startswith("input/")]
    shape = policy if policy is not None else inference.model  # what the policy reads, at what sizes
    sizes = shape.image_sizes
    for key, (h, w) in sizes.items():
        have = inputs.get(f"input/{key}")
        if have is None or tuple(have.shape[1:3]) != (h, w):
            raise ReplayInputError(f"the model reads {key} at {h}x{w} but the run recorded "
                                   f"{'no ' + key if have is None else 'x'.join(map(str, have.shape[1:3]))}; "
                                   "replay with a model of the run's input sizes")
    wanted = [*sizes, *(getattr(shape, "lowdim_sizes", None) or {})]
    missing = [k for k in wanted if k not in keys]
    if missing:
        raise ReplayInputError(f"the run recorded no {missing[0]!r} input, which the model reads; replay a model "
                               "that reads the run's inputs")
    predicted, attention = _recorded_outputs(episode)
    steps = int(inputs["step"].shape[0])
    stored = min(steps, predicted.shape[0], attention.shape[0])  # a committed baseline may keep fewer steps
    task = TaskPrompt.of(str(inputs["instruction"]), goals)
    seed = int(inputs["seed"])
    entries = [{k: inputs[f"input/{k}"][t] for k in wanted} for t in range(steps)]
    inferred = [t for t in range(stored) if bool(inputs["inferred"][t])]
    chunks, readout = [], []
    for t in inferred:
        obs = window_from_entries(entries[:t + 1], window, wanted)
        (result,) = inference([InferenceRequest(obs, task, seed, int(inputs["step"][t]))])
        chunks.append(result.chunk)
        readout.append(result.readout_attention)
    out = {"task": episode.task, "episode": episode.episode, "seed": seed, "steps": steps, "compared_steps": len(inferred)}
    if not inferred:
        return EpisodeReplay(**out, verdict=ReplayVerdict.EQUIVALENT, first_changed_step=None, action_change_max=0.0,
                             attention_js_max=0.0)
    recorded_chunks = predicted[inferred]
    if recorded_chunks.shape[1:] != np.shape(chunks[0]):
        return EpisodeReplay(**out, verdict=ReplayVerdict.CHANGED, first_changed_step=inferred[0], action_change_max=None,
                             attention_js_max=None, note=f"action chunks differ in shape: {recorded_chunks.shape[1:]} "
                                                         f"recorded, {np.shape(chunks[0])} replayed")
    statistics = getattr(inference, "statistics", None)  # the unnormalisation statistics (a served policy: its own)
    scale = action_scale(statistics, inference.config.action_normalization, recorded_chunks.shape[-1])
    actions = action_change(recorded_chunks, np.stack(chunks), scale)  # (compared,)
    recorded_attention = attention[inferred]
    if readout[0] is None:  # the replayed policy gives no attention (a served one): its actions are what is compared
        js = np.zeros((len(inferred), 1, 1))
        note = "the replayed policy gives no attention: actions compared only"
    elif recorded_attention.shape[1:] == np.shape(readout[0]):
        js = attention_change(recorded_attention, np.stack(readout))  # (compared, layers, heads)
        note = None
    else:
        js = np.full((len(inferred), 1, 1), np.inf)
        note = f"attention shapes differ: {recorded_attention.shape[1:]} recorded, {np.shape(readout[0])} replayed"
    first = first_change(actions, js, tolerances)
    measured = readout[0] is not None  # attention compared (else only actions: the keys say nothing of attention)
    return EpisodeReplay(
        **out, verdict=ReplayVerdict.EQUIVALENT if first is None else ReplayVerdict.CHANGED,
        first_changed_step=None if first is None else inferred[first],
        action_change_max=float(actions.max()), attention_js_max=float(js.max()) if measured else None,
        action_change_step0=float(actions[0]), attention_js_step0=float(js[0].max()) if measured else ABSENT,
        action_change_per_step=tuple(actions.tolist()),
        attention_js_per_step=tuple(js.reshape(len(inferred), -1).max(axis=1).tolist()) if measured else ABSENT,
        change_at_first=(ABSENT if first is None else
                         ChangeAt(action=float(actions[first]), attention_js=float(js[first].max()) if measured else None)),
        note=note or ABSENT)


def replay_run(run_dir: str | Path, model_source: str | None = None, gate: GateConfig | None = None,
               loaded_model=None) -> ReplayResult:
    """Replay every finished episode of a run with recorded inputs (see the module docstring); returns replay.json's
    content.

    gate: the tolerances and the replayed model's text_tokenizer, auto|fallback|PATH (None: the run's own choice)."""
    from harness.policies import as_policy
    from harness.run.protocol import load_protocol_policy
    from harness.policy import resize_frame
    from harness.run import checks

    gate = gate if gate is not None else GateConfig()
    tolerances, text_tokenizer = gate.tolerances(), gate.text_tokenizer
    run = load_run(run_dir)
    if run.format == "legacy":
        raise ReplayInputError(f"{run.path} was made before the run store and recorded no inputs; re-run it with "
                               "--record-inputs")
    protocol = protocol_from_manifest(run.manifest, run.path / "manifest.json")
    if not run.attention:
        raise no_attention_error(run)
    episodes = [e for e in run.episodes if e.ok]
    if not episodes:
        raise ReplayInputError(f"{run.path} has no finished episode to replay; finish the run first")
    for e in episodes:  # before the model loads: every episode must have its inputs
        inputs_path(e)
    source = model_source or protocol.model
    if model_source is None and Path(source).is_absolute() and not Path(source).exists():
        raise ReplayInputError(f"the run's model {source} is not on this machine (a run copied from elsewhere); "
                               "pass the model to replay with --model")
    # the run's text tokenizer choice (auto, fallback or a file) with whichever model is replayed, unless the gate names
    # one: the same instruction must become the same tokens, or the comparison measures the tokenizer
    model = (as_policy(loaded_model) if loaded_model is not None
             else load_protocol_policy(protocol, source, text_tokenizer))
    config = dataclasses.replace(protocol.policy, inference_batch=1)
    if gate.drop_probes:
        from harness.policy_config import without_probes

        config = without_probes(config)
    if config.intervention is not None:
        from harness.interventions import parse_intervention

        if parse_intervention(config.intervention).masks:  # the recorded inputs are the masked frames already
            config = dataclasses.replace(config, intervention=None)
    inference = model.inference(config)
    goals = None
    if protocol.goal_images:
        images = checks.decode_goal_images(protocol.goal_images)
        goals = {k: resize_frame(v, model.goal_image_sizes[k]) for k, v in images.items() if k in model.goal_image_sizes}
    results = [replay_episode(inference, e, int(model.window_size), goals, tolerances, model) for e in episodes]
    changed = [r for r in results if r.verdict != ReplayVerdict.EQUIVALENT]
    first = min(changed, key=lambda r: r.first_changed_step if r.first_changed_step is not None else 0) if changed else None
    finite = lambda xs: [x for x in xs if x is not None]  # noqa: E731
    return ReplayResult(
        format=FORMAT,
        verdict=ReplayVerdict.CHANGED if changed else ReplayVerdict.EQUIVALENT,
        run=str(run.path),
        recorded_model=run.model.source,
        recorded_model_fingerprint=protocol.model_fingerprint,
        model=source,
        tolerances=tolerances,
        units={"action": "max |change| over the chunk, normalised action units",
               "attention": "max Jensen-Shannon divergence (bits) over layers and heads, float16"},
        platform_recorded=run.manifest.get("platform_fingerprint"),
        episodes=len(results),
        episodes_changed=len(changed),
        steps_compared=sum(r.compared_steps for r in results),
        action_change_max=max(finite([r.action_change_max for r in results]), default=None),
        attention_js_max=max(finite([r.attention_js_max for r in results]), default=None),
        first_change=None if first is None else FirstChange(
            task=first.task, episode=first.episode, first_changed_step=first.first_changed_step,
            change_at_first=first.change_at_first or None, note=first.note or None),
        episode_details=tuple(results),
    )


def summary_text(result: ReplayResult) -> str:
    """A few lines for the terminal / CI log."""
    tol = result.tolerances
    lines = [f"replay: {result.verdict}: {result.model} on the inputs of {result.episodes} episodes "
             f"({result.steps_compared} inferred steps) recorded by {result.recorded_model}",
             f"  largest change: action {_fmt(result.action_change_max)} (tolerance {tol.action:g} normalised units), "
             f"attention JS {_fmt(result.attention_js_max)} (tolerance {tol.attention_js:g} bits)"]
    first = result.first_change
    if first is not None:
        at = first.change_at_first
        lines.append(f"  first change: {first.task} episode {first.episode} step {first.first_changed_step}: "
                     f"action {_fmt(at.action if at else None)}, attention JS {_fmt(at.attention_js if at else None)}"
                     + (f" ({first.note})" if first.note else ""))
    return "\n".join(lines)


def _fmt(x) -> str:
    return "n/a" if x is None else f"{x:.3g}"


def exit_code(result: ReplayResult) -> int:
    return ReplayVerdict(result.verdict).exit_code  # EQUIVALENT 0, CHANGED 1

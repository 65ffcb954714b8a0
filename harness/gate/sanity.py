"""`octo-harness sanity RUN [RUN...]`: the attribution methods' sanity checks, once per policy, open loop on the
inputs runs recorded (`--record-inputs`), so the trained and the randomised policy see exactly the same frames and rng.

Every `every`-th inferred step of every finished episode (harness.analysis.sanity):
- model-parameter randomisation, cascading (top down) and each block alone: Spearman and SSIM of the trained
  and randomised maps per method and camera, means with 95% intervals over steps, and the pass/fail verdict;
- with `additivity`: per camera and fill, the single-patch effects (occlusion), the whole camera's deletion, and how
  additive they are for nested top-k sets of the occlusion ranking and of a random ranking.

Writes <out>/sanity.json (settings, summaries, verdicts, per-step rows), randomisation.csv and additivity.csv
atomically; returns the result dict. The model is the runs' own unless `model_source` is given.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import logging
import math
import time
from pathlib import Path

import numpy as np

from harness.analysis import sanity as S
from harness.measures.attribution import (METHODS, OctoFunctions, analyse, attribute, needs_gradients, needs_occlusion,
                                          parse_methods)
from harness.measures.faithfulness import FILLS, k_values, ranking
from harness.analysis.runs import load_run
from harness.gate.replay import ReplayInputError, inputs_path, recorded_inputs
from harness.options import option
from harness.run.protocol import protocol_from_manifest

log = logging.getLogger(__name__)

FORMAT = "octo-harness-sanity/1"
# sanity's own default: every method of the table (harness.measures.attribution.METHODS) but the random control,
# which is always added; so occlusion too, unlike a run's default: it is the reference the checks compare maps with
DEFAULT_METHODS = ",".join(name for name, method in METHODS.items() if not method.control)
RANDOMISATION_COLUMNS = ("schedule", "stage", "method", "camera", "steps", "spearman", "spearman_low", "spearman_high",
                         "ssim", "ssim_low", "ssim_high", "verdict")
ADDITIVITY_COLUMNS = ("task", "camera", "fill", "steps", "whole_change", "single_max", "single_sum", "single_sum_over_whole",
                      "set", "k", "change", "sum_single", "additivity", "cosine")


def _fills(value) -> tuple[str, ...] | None:
    """--fills "mean,blur" (or a list) -> ("mean", "blur"); none named -> None (the default)."""
    names = tuple(f.strip() for f in (value.split(",") if isinstance(value, str) else value) if f.strip())
    return names or None


@dataclasses.dataclass(frozen=True)
class SanityOptions:
    """The options of `octo-harness sanity`, each declared once (harness.options): the flags and their [defaults]."""

    every: int = option(10, "--every", "every k-th inferred step of each episode", type=int)  # steps 0, k, 2k, ...
    max_steps: int | None = option(None, "--max-steps", "at most N steps in all", type=int,
                                   default_text="every selected step")
    methods: str = option(DEFAULT_METHODS, "--methods", "attribution methods (as for run --attribution; random is "
                          "always added)", convert=lambda v: v or None)
    additivity: bool = option(False, "--additivity", "also measure single-patch effects and how additive they are, "
                              "per camera and fill", action="store_true", convert=bool)
    fills: tuple[str, ...] = option(FILLS, "--fills", "fills of the additivity measures, comma-separated",
                                    convert=_fills)
    seed: int = option(0, "--seed", "seed of the re-drawn weights and the random orders", type=int)

    def __post_init__(self):
        if self.every < 1:
            raise ValueError(f"--every must be >= 1, got {self.every}")
        bad = [f for f in self.fills if f not in FILLS]
        if bad:
            raise ValueError(f"unknown fill {bad[0]!r}; use {', '.join(FILLS)}")


def _steps(runs: list[Path], every: int):
    """[(run, episode, inputs)] of every finished episode with recorded inputs (checked before the model loads)."""
    out = []
    for path in runs:
        run = load_run(path)
        if run.format == "legacy":
            raise ReplayInputError(f"{run.path} was made before the run store and recorded no inputs; re-run it with "
                                   "--record-inputs")
        episodes = [e for e in run.episodes if e.ok]
        if not episodes:
            raise ReplayInputError(f"{run.path} has no finished episode; finish the run first")
        for e in episodes:
            inputs_path(e)
        out.append((run, episodes))
    return out


def run_sanity(runs: list[str | Path], out: str | Path, options: SanityOptions = SanityOptions(),
               model_source: str | None = None, loaded_model=None) -> dict:
    """Check the attribution methods on the runs' recorded inputs (see the module docstring); writes and returns
    the result. loaded_model: the model of `model_source` (or of the runs) already loaded."""
    from harness.files import atomic_write_json, write_atomic
    from harness.policies import as_policy
    from harness.run.protocol import load_protocol_policy

    start = time.perf_counter()
    runs = [Path(r) for r in runs]
    loaded = _steps(runs, options.every)
    protocol = _common_protocol(loaded, model_source)
    source = model_source or protocol.model
    model = as_policy(loaded_model) if loaded_model is not None else load_protocol_policy(protocol, source)
    config = dataclasses.replace(protocol.policy, inference_batch=1, intervention=None, attribution=None,
                                 faithfulness_every=0)
    # the attribution methods read the policy's own function (its parameters, its transformer): an Octo checkpoint
    model.require({"octo-harness sanity": "interventions"})
    inference = model.inference(config)
    functions = OctoFunctions(model.model)
    methods = parse_methods(options.methods, functions.layers)
    blocks = S.octo_blocks(functions.params)
    stages = S.schedules(blocks)
    variants = [(schedule, stage, S.randomised_params(functions.params, paths, options.seed))
                for schedule, stage, paths in stages]
    last_stage = [stage for schedule, stage, _ in stages if schedule == "cascading"][-1]
    found = _compare_steps(loaded, model, inference, functions, methods, variants, options)
    if not found.count:
        raise ReplayInputError(f"no inferred step is a multiple of --every {options.every} in the runs given")
    summary = S.summarise_randomisation(found.per_step, seed=options.seed)
    verdicts = S.verdict(summary, last_stage)
    for row in summary:
        row["verdict"] = verdicts.get((row["method"], row["camera"]), "") if row["stage"] == last_stage else ""
    additivity = _summarise_effects(found.effects)
    result = {
        "format": FORMAT,
        "model": source,
        "model_fingerprint": protocol.model_fingerprint,
        "runs": [str(r.path) for r, _ in loaded],
        "steps": found.count,
        "options": dataclasses.asdict(options),
        "blocks": [{"name": name, "paths": ["/".join(p) for p in paths]} for name, paths in blocks],
        "rule": f"pass: with every block randomised ({last_stage}), the upper 95% bound of the mean Spearman "
                f"correlation between trained and randomised maps is below {S.PASS_BELOW}",
        "verdicts": [{"method": m, "camera": c, "verdict": v} for (m, c), v in verdicts.items()],
        "randomisation": summary,
        "additivity": additivity,
        **_agreement_and_profile(found, options.seed),
        "per_step": found.per_step,
        "seconds": time.perf_counter() - start,
    }
    out = Path(out)
    write_atomic(out / "randomisation.csv", lambda f: f.write(_csv(RANDOMISATION_COLUMNS, summary)))
    write_atomic(out / "additivity.csv", lambda f: f.write(_csv(ADDITIVITY_COLUMNS, additivity)))
    atomic_write_json(out / "sanity.json", result)
    return result


def _common_protocol(loaded: list, model_source: str | None):
    """The first run's protocol; every run must have been made with its model, unless another model is given."""
    first = loaded[0][0]
    protocol = protocol_from_manifest(first.manifest, first.path / "manifest.json")
    for run, _ in loaded[1:]:
        other = protocol_from_manifest(run.manifest, run.path / "manifest.json")
        if model_source is None and other.model_fingerprint != protocol.model_fingerprint:
            raise ReplayInputError(f"{run.path} was made with another model than {first.path}; check one policy at a "
                                   "time (or pass --model)")
    return protocol


@dataclasses.dataclass
class _Found:
    """What the selected steps gave: randomisation rows per step, additivity effects, agreement with occlusion,
    per-patch map shares {(camera, method): [grids]}, the frames {camera: [(frame, grid shape)]}, the step count."""
    per_step: list = dataclasses.field(default_factory=list)
    effects: list = dataclasses.field(default_factory=list)
    agreement: list = dataclasses.field(default_factory=list)
    profiles: dict = dataclasses.field(default_factory=dict)
    frames: dict = dataclasses.field(default_factory=dict)
    count: int = 0


def _compare_steps(loaded: list, model, inference, functions, methods, variants: list, options: SanityOptions) -> _Found:
    """Every `every`-th inferred step of every episode (at most `max_steps` in all): the trained maps against each
    randomised variant's, the occlusion agreement and profiles, and (with `additivity`) the patch effects."""
    from harness.policy import InferenceRequest, TaskPrompt, window_from_entries

    window = int(model.window_size)
    wanted = [*model.image_sizes, *getattr(model, "lowdim_sizes", {})]
    gradients, occlusion = needs_gradients(methods), needs_occlusion(methods)
    found = _Found()
    for run, episodes in loaded:
        for episode in episodes:
            inputs = recorded_inputs(episode)
            _check_recorded_sizes(model, inputs, run)
            task = TaskPrompt.of(str(inputs["instruction"]))
            seed = int(inputs["seed"])
            entries = [{k: inputs[f"input/{k}"][t] for k in wanted} for t in range(int(inputs["step"].shape[0]))]
            for t in range(len(entries)):
                step = int(inputs["step"][t])
                if not bool(inputs["inferred"][t]) or step % options.every:
                    continue
                if options.max_steps is not None and found.count >= options.max_steps:
                    break
                found.count += 1
                obs = window_from_entries(entries[:t + 1], window, wanted)
                observations, tasks, keys = inference._inputs([InferenceRequest(obs, task, seed, step)])
                where = {"task": episode.task, "episode": episode.episode, "step": step}
                fn = functions.at(observations, tasks, keys[0])
                trained_analysis = analyse(fn, gradients=gradients, occlusion=occlusion)
                trained = {m: attribute(trained_analysis, m, seed=[seed, step]) for m in methods}
                _profile(trained, fn.images, where, found.agreement, found.profiles, found.frames)
                for schedule, stage, params in variants:
                    a = analyse(functions.at(observations, tasks, keys[0], params=params), gradients=gradients,
                                occlusion=occlusion)
                    randomised = {m: attribute(a, m, seed=[seed, step]) for m in methods}
                    for row in S.compare_maps(trained, randomised):
                        found.per_step.append({**where, "schedule": schedule, "stage": stage, **row})
                if options.additivity:
                    found.effects += _effects(fn, trained_analysis, options, where, seed, step)
    return found


def _check_recorded_sizes(model, inputs, run) -> None:
    """The recorded frames of every camera the model reads are at its sizes (ReplayInputError, one line)."""
    for key, (h, w) in model.image_sizes.items():
        have = inputs.get(f"input/{key}")
        if have is None or tuple(have.shape[1:3]) != (h, w):
            raise ReplayInputError(f"the model reads {key} at {h}x{w} but {run.path} recorded "
                                   f"{'no ' + key if have is None else 'x'.join(map(str, have.shape[1:3]))}")


def _agreement_and_profile(found: _Found, seed: int) -> dict:
    """{"occlusion_agreement": each method's Spearman with occlusion over steps, "patch_profile": each map's mean
    share per patch, and each camera's pixel spread per patch over the steps}."""
    occlusion_agreement = S.summarise_randomisation(
        [{**r, "schedule": "occlusion", "stage": "trained"} for r in found.agreement], seed=seed)
    patch_profile = [{"camera": camera, "method": method, "map_share": (np.mean(grids, axis=0)).round(4).tolist()}
                     for (camera, method), grids in found.profiles.items()]
    patch_profile += [{"camera": camera, "method": "pixel std over steps",
                       "map_share": np.asarray(stack).std(axis=0).mean(axis=-1).round(2).tolist()}
                      for camera, stack in ((c, _patch_means(f)) for c, f in found.frames.items())]
    return {"occlusion_agreement": [{k: r[k] for k in ("method", "camera", "steps", "spearman", "spearman_low",
                                                       "spearman_high")} for r in occlusion_agreement],
            "patch_profile": patch_profile}


def _effects(fn, analysis, options: SanityOptions, where: dict, seed: int, step: int) -> list[dict]:
    """Per camera and fill: single-patch effects, whole deletion, additivity of nested occlusion-ranked and random sets."""
    from harness.measures.attribution import occlusion_maps

    rows = []
    for _, key, r, c in analysis.tokens.image_groups:
        n = r * c
        ks = sorted({*k_values(n, (1, 2, 0.25, 0.5)), n})
        window = np.asarray(fn.images[key], np.float32)

        def evaluate(frames, key=key, window=window):
            inputs = {k: np.repeat(np.asarray(v, np.float32)[None], len(frames), axis=0) for k, v in fn.images.items()}
            inputs[key][:, -1] = frames
            return fn.batch(inputs)

        for fill in options.fills:
            single = occlusion_maps(fn, analysis.actions, fill)[key] if fill != "mean" or analysis.occlusion is None \
                else analysis.occlusion[key]
            random_order = np.random.default_rng([seed, step, 3]).permutation(n)
            sets = {"occlusion": S.nested_sets(ranking(single), ks, r, c), "random": S.nested_sets(random_order, ks, r, c)}
            got = S.patch_effects(evaluate, window[-1], analysis.actions, sets, fill=fill, seed=[seed, step, 5])
            for name in sets:
                for j, k in enumerate(ks):
                    rows.append({**where, "camera": key, "fill": fill, "whole": got["whole"],
                                 "single_max": float(got["single"].max()), "single_sum": float(got["single"].sum()),
                                 "set": name, "k": int(k), "change": float(got[name]["change"][j]),
                                 "sum_single": float(got[name]["sum_single"][j]),
                                 "additivity": float(got[name]["additivity"][j]), "cosine": float(got[name]["cosine"][j])})
    return rows


def _profile(trained: dict, images: dict, where: dict, agreement: list, profiles: dict, frames: dict) -> None:
    """Per camera: each method's Spearman correlation with occlusion (the single-patch effects) at this step, each
    map's share of its total per patch, and the current frame (for the patches' pixel spread over steps)."""
    occlusion = trained.get("occlusion", {})
    for method, by_camera in trained.items():
        for camera, m in by_camera.items():
            total = float(np.sum(m))
            if total > 0:
                profiles.setdefault((camera, method), []).append(np.asarray(m, np.float64) / total)
            if method != "occlusion" and camera in occlusion:
                agreement.append({"method": method, "camera": camera, "spearman": S.spearman(m, occlusion[camera]),
                                  "ssim": S.ssim(m, occlusion[camera])})
    for camera in next(iter(trained.values()), {}):
        frames.setdefault(camera, []).append((np.asarray(images[camera][-1], np.float32),
                                              np.asarray(next(iter(trained.values()))[camera]).shape))


def _patch_means(frames: list) -> np.ndarray:
    """[(frame (H, W, 3), (rows, cols))] -> (steps, rows, cols, 3) mean colour of each patch."""
    from harness.measures.attention import patch_index

    out = []
    for frame, (rows, cols) in frames:
        h, w = frame.shape[:2]
        index = patch_index(h, rows)[:, None] * cols + patch_index(w, cols)[None, :]
        sums = np.stack([np.bincount(index.ravel(), weights=frame[..., ch].ravel(), minlength=rows * cols)
                         for ch in range(3)], axis=-1)
        counts = np.bincount(index.ravel(), minlength=rows * cols)[:, None]
        out.append((sums / counts).reshape(rows, cols, 3))
    return np.stack(out)


def _summarise_effects(rows: list[dict]) -> list[dict]:
    """Medians over steps per (task, camera, fill, set, k)."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault((row["task"], row["camera"], row["fill"], row["set"], row["k"]), []).append(row)
    out = []
    for (task, camera, fill, name, k), items in groups.items():
        med = lambda key: float(np.nanmedian([r[key] for r in items]))  # noqa: E731
        whole, single_sum = med("whole"), med("single_sum")
        out.append({"task": task, "camera": camera, "fill": fill, "steps": len(items), "whole_change": whole,
                    "single_max": med("single_max"), "single_sum": single_sum,
                    "single_sum_over_whole": float(np.nanmedian([r["single_sum"] / r["whole"] if r["whole"] > 0 else np.nan
                                                                 for r in items])),
                    "set": name, "k": k, "change": med("change"), "sum_single": med("sum_single"),
                    "additivity": med("additivity"), "cosine": med("cosine")})
    return out


def _csv(columns, rows) -> bytes:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow(["" if isinstance(v, float) and not math.isfinite(v) else f"{v:.6g}" if isinstance(v, float) else v
                         for v in (row.get(c, "") for c in columns)])
    return buffer.getvalue().encode()


def markdown(result: dict) -> str:
    """The randomisation table (cascading stages and each block alone), the verdicts and the additivity table."""
    lines = [f"Model-parameter randomisation of {result['model']} on {result['steps']} steps "
             f"({', '.join(Path(r).name for r in result['runs'])}). {result['rule']}.", "",
             "| schedule | stage | method | camera | steps | Spearman [95%] | SSIM [95%] | verdict |",
             "|---|---|---|---|---:|---|---|---|"]
    f = lambda m, lo, hi: "n/a" if not math.isfinite(m) else f"{m:.2f} [{lo:.2f}, {hi:.2f}]"  # noqa: E731
    for r in result["randomisation"]:
        lines.append(f"| {r['schedule']} | {r['stage']} | {r['method']} | {r['camera']} | {r['steps']} | "
                     f"{f(r['spearman'], r['spearman_low'], r['spearman_high'])} | "
                     f"{f(r['ssim'], r['ssim_low'], r['ssim_high'])} | {r.get('verdict', '')} |")
    if result.get("occlusion_agreement"):
        lines += ["", "Agreement of each trained map with occlusion (single-patch effects, mean fill): Spearman [95%] "
                      "over steps.", "", "| method | camera | steps | Spearman with occlusion [95%] |", "|---|---|---:|---|"]
        for r in result["occlusion_agreement"]:
            lines.append(f"| {r['method']} | {r['camera']} | {r['steps']} | "
                         f"{f(r['spearman'], r['spearman_low'], r['spearman_high'])} |")
    if result.get("patch_profile"):
        lines += ["", "Where each map puts its weight (mean share per patch, rows top to bottom), and how much each "
                      "patch's mean colour varies over the steps (pixel levels):", ""]
        for r in result["patch_profile"]:
            grid = " / ".join(" ".join(f"{v:.2f}" for v in row) for row in r["map_share"])
            lines.append(f"- {r['camera']}, {r['method']}: {grid}")
    if result["additivity"]:
        lines += ["", "| task | camera | fill | steps | whole camera | largest single | sum of singles / whole | set | k | "
                      "change(set) | sum of single changes | additivity | cosine |",
                  "|---|---|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|"]
        for r in result["additivity"]:
            lines.append(f"| {r['task']} | {r['camera']} | {r['fill']} | {r['steps']} | {r['whole_change']:.3f} | "
                         f"{r['single_max']:.3f} | {r['single_sum_over_whole']:.2f} | {r['set']} | {r['k']} | "
                         f"{r['change']:.3f} | {r['sum_single']:.3f} | {r['additivity']:.2f} | {r['cosine']:.2f} |")
    return "\n".join(lines)

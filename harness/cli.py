"""Command line: `octo-harness run ...` (closed-loop evaluation with attention capture) and `octo-harness tasks`.

Only parses arguments into frozen configs, wires the runner and prints; user errors are one line.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, KeyError, FileNotFoundError, PermissionError)


def _user_errors() -> tuple[type[BaseException], ...]:
    from envs.gl import HeadlessGLError
    from harness.octo.errors import OctoError
    from harness.run.store import RunLockedError

    return (*USER_ERRORS, RunLockedError, OctoError, HeadlessGLError)


def _interrupt(signum, frame):
    """SIGTERM before the run installs its own handler (loading the model, compiling): the same exit as later."""
    exc = KeyboardInterrupt(signal.Signals(signum).name)
    exc.signum = signum
    raise exc


def _video_attention(text: str):
    from harness.outputs.writers import ATTRIBUTION_VIDEO

    if text in ("rollout", *ATTRIBUTION_VIDEO):
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--video-attention takes a layer index, 'rollout' or one of "
                                         f"{', '.join(ATTRIBUTION_VIDEO)}, got {text!r}") from None


def _add_execution_args(parser: argparse.ArgumentParser) -> None:
    """Where a run's episodes execute (not part of the protocol: a run may resume with another worker count)."""
    parser.add_argument("--workers", type=int, default=None,
                        help="env worker processes, inference batched in one process (same episodes as a sequential run) "
                             "[none: sequential; with --executor ray: the CPU count, minus one per replica on a cluster]")
    parser.add_argument("--executor", choices=["local", "ray"], default=None,
                        help="where the env workers run: local processes or Ray actors (pip install 'octo-harness[ray]') [local]")
    parser.add_argument("--ray-address", default=None,
                        help="Ray cluster to join (e.g. auto or head-node:6379); --out must be on a filesystem every node "
                             "mounts [start a local Ray instance]")
    parser.add_argument("--policy-replicas", type=int, default=None, help="Ray: model replicas serving the env workers [1]")


def _execution(args):
    """The executor factory the execution flags of `_add_execution_args` ask for (None: sequential)."""
    from harness.run.execution import executor_factory

    return executor_factory(args.workers, args.executor, args.ray_address, args.policy_replicas)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="octo-harness", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show tracebacks for errors")
    parser.add_argument("--verbose", action="store_true",
                        help="also show other libraries' INFO lines and start-up warnings (hidden by default)")
    sub = parser.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run (or resume) closed-loop episodes and record attention",
                       description="Run the episodes of an evaluation protocol into <out>/<run-name>; running the same "
                                   "command again resumes it. Defaults are shown in brackets.")
    r.add_argument("--protocol", type=Path, default=None,
                   help="TOML file whose keys mirror these flags (task, model, episodes, ...); flags given here override it")
    r.add_argument("--resume", type=Path, default=None, metavar="RUN_DIR",
                   help="continue the run in RUN_DIR with the protocol from its manifest.json")
    r.add_argument("--overwrite", action="store_true", help="start the run afresh, deleting what the run folder holds")
    r.add_argument("--retry-failed", action="store_true", help="on resume, run episodes that failed with an error again")
    r.add_argument("--task", action="append", default=None,
                   help="task name (repeat or comma-separate for several; 'all' for every registered task)")
    r.add_argument("--episodes", type=int, default=None, help="episodes per task [1]")
    r.add_argument("--model", default=None,
                   help="hf://owner/name, a local checkpoint folder, or random:octo-small-1.5 / random:octo-base-1.5 "
                        "[hf://rail-berkeley/octo-small-1.5]")
    r.add_argument("--max-steps", type=int, default=None, help="stop each episode after N control steps [task's limit]")
    r.add_argument("--out", type=Path, default=None, help="output root [results/runs]")
    r.add_argument("--run-name", default=None,
                   help="folder name of this run [<model>_<protocol hash>: the same command resumes the same run]")
    r.add_argument("--seed", type=int, default=None, help="episode k uses seed + k [0]")
    r.add_argument("--instruction", default=None, help="override the task's language instruction")
    r.add_argument("--dataset-key", default=None,
                   help="dataset statistics used to unnormalise actions (default: bridge_dataset when present)")
    r.add_argument("--execution", choices=["temporal_ensemble", "receding_horizon"], default=None,
                   help="[temporal_ensemble]")
    r.add_argument("--receding-steps", type=int, default=None, help="actions executed per inference (receding horizon) [4]")
    r.add_argument("--ensemble-weight", type=float, default=None, help="temporal ensemble weight exp(-w*i); 0 = mean [0]")
    r.add_argument("--png-every", type=int, default=None, help="write overlays every n-th step (0 = none) [1]")
    r.add_argument("--layers", default=None, help="overlay layers, e.g. 0,5,11 [all]")
    r.add_argument("--video-attention", type=_video_attention, default=None,
                   help="attention shown in the MP4: a layer index (default -1 = last), 'rollout', or an attribution "
                        "map: grad-attention, saliency, occlusion (computed at every step, as --attribution)")
    r.add_argument("--normalisation", choices=["frame", "episode"], default=None, help="[frame]")
    r.add_argument("--no-video", action="store_true", default=None)
    r.add_argument("--gif", action="store_true", default=None, help="also write rollout.gif")
    r.add_argument("--bbox", action="store_true", default=None, help="draw the target object's bounding box on overlays")
    r.add_argument("--no-masks", action="store_true", default=None, help="do not render target/robot masks")
    r.add_argument("--record-inputs", action="store_true", default=None,
                   help="write each episode's policy inputs (inputs.npz: resized frames, proprio, seed, instruction; "
                        "compressed) so `octo-harness replay` can run any model open loop on them")
    r.add_argument("--goal-images", type=Path, default=None,
                   help="folder with <obs key>.png goal images (image_primary.png, ...) for goal-conditioned models")
    r.add_argument("--fast-render", action="store_true", default=None,
                   help="render without reflections, shadows and anti-aliasing (~3.6x faster frames)")
    r.add_argument("--camera", action="append", default=None, metavar="KEY=camera:size",
                   help="observation key fed by a robosuite camera at a square size, e.g. image_primary=agentview:84 "
                        "(repeat; default: the task's cameras or the checkpoint's harness.toml)")
    r.add_argument("--image-convention", choices=["upright", "opengl"], default=None,
                   help="orientation of the frames the model was trained on [upright]")
    r.add_argument("--action-space", choices=["octo-delta", "robosuite"], default=None,
                   help="what the model's actions mean [octo-delta, or the checkpoint's harness.toml]")
    r.add_argument("--hold-gripper", default=None, metavar="open|closed|VALUE",
                   help="for a 6-D (arm-only) model: the env takes 6-D actions and holds the gripper at this value "
                        "(octo-delta: 1 open, 0 closed; robosuite: -1 open, +1 closed); part of the protocol")
    r.add_argument("--sampler", choices=["latest", "v0.1.0"], default=None,
                   help="diffusion sampling as the latest original Octo code does, or as v0.1.0 did [latest]")
    r.add_argument("--action-normalization", choices=["normal", "bounds"], default=None,
                   help="how actions are unnormalised: mean/std or p01/p99 bounds [checkpoint's harness.toml, else normal]")
    r.add_argument("--proprio-normalization", choices=["normal", "bounds", "none"], default=None,
                   help="how proprio inputs are normalised [checkpoint's harness.toml, else normal]")
    r.add_argument("--intervene", default=None, metavar="SPEC",
                   help="closed-loop intervention at every step (part of the protocol): mask-top:K:METHOD[:LAYER][@CAMERA], "
                        "mask-bottom:K:METHOD[:LAYER][@CAMERA], mask-random:K[@CAMERA], mask-all[@CAMERA], "
                        "ablate-heads:L:H[,L:H...] (METHOD: attention, rollout, grad-attention, saliency)")
    r.add_argument("--attribution", default=None, metavar="METHODS",
                   help="store attribution maps at every inference step in attribution.npz: comma-separated attention "
                        "(every layer; attention:L one), rollout, grad-attention, saliency; random is always added")
    r.add_argument("--faithfulness-every", type=int, default=None, metavar="K",
                   help="open-loop faithfulness (deletion/insertion curves, top/random/bottom-k) of every attribution "
                        "method every K-th step, in faithfulness.jsonl [0 = never; methods default to all]")
    r.add_argument("--faithfulness-fill", choices=["mean", "blur"], default=None,
                   help="what a deleted patch becomes in the faithfulness curves [mean]")
    r.add_argument("--verbose", action="store_true", default=argparse.SUPPRESS,
                   help="also show other libraries' INFO lines and start-up warnings")
    r.add_argument("--text-tokenizer", default=None, metavar="auto|fallback|PATH",
                   help="text tokenizer: the checkpoint's own (t5-base from the Hugging Face cache), the deterministic "
                        "fallback (not T5), or a tokenizer.json / folder; part of the model fingerprint [auto]")
    r.add_argument("--inference-batch", type=int, default=None,
                   help="examples per compiled inference call; every call is padded to it, so actions are bit-identical "
                        "whatever --workers or the load (part of the protocol; >1 pays on a GPU) [1]")
    r.add_argument("--perturb", default=None, metavar="KIND[@KEY]:LEVEL[,...]",
                   help="controlled perturbation of the scene (part of the protocol; docs/perturbations.md): camera, "
                        "lighting, texture, distractors, init-state, noise, language at level 0 (nominal) to 5; "
                        "camera@KEY / noise@KEY pick a camera, e.g. camera:3,lighting:1 [none]")
    r.add_argument("--ci-method", choices=["wilson", "clopper-pearson"], default=None,
                   help="confidence interval of success rates (95%%) [wilson]")
    _add_execution_args(r)

    sub.add_parser("tasks", help="list the registered tasks")

    rob = sub.add_parser("robustness", help="run a grid of perturbation kinds x levels x tasks into one folder of runs",
                         description="One run per (kind, level > 0) over every task, plus one nominal run for level 0 "
                                     "(docs/perturbations.md); resumable: the same command finishes what is missing. "
                                     "`octo-harness report OUT/*/` then adds a Robustness section.")
    rob.add_argument("--model", required=True, help="model (as for `run --model`)")
    rob.add_argument("--task", action="append", required=True, help="task name(s), repeat or comma-separate")
    rob.add_argument("--perturb", required=True, metavar="KINDS",
                     help="comma-separated kinds (camera, lighting, texture, distractors, init-state, noise, language; "
                          "camera@KEY / noise@KEY for one camera)")
    rob.add_argument("--levels", default="0,1,3,5", help="comma-separated levels 0-5 (0 = the nominal run) [0,1,3,5]")
    rob.add_argument("--episodes", type=int, default=20, help="episodes per task and condition [20]")
    rob.add_argument("--seed", type=int, default=None, help="episode k uses seed + k in every condition [0]")
    rob.add_argument("--max-steps", type=int, default=None, help="stop each episode after N control steps [task's limit]")
    rob.add_argument("--out", type=Path, default=Path("results/robustness"), help="grid folder [results/robustness]")
    rob.add_argument("--protocol", type=Path, default=None, help="TOML protocol file for every other run setting")
    rob.add_argument("--fast-render", action="store_true", default=None, help="as for `run --fast-render`")
    rob.add_argument("--png-every", type=int, default=0, help="overlay PNGs every n-th step (0 = none) [0]")
    rob.add_argument("--no-video", action="store_true", default=None, help="no rollout.mp4 per episode")
    rob.add_argument("--overwrite", action="store_true", help="start every run of the grid afresh")
    _add_execution_args(rob)

    rep = sub.add_parser("report", help="HTML report comparing attention task by task (one or more runs)",
                         description="Aggregate the episodes of one or more runs into report.html (self-contained), "
                                     "tables/*.csv (long format) and plots/*.png.")
    rep.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR", help="run folder(s); several appear side by side")
    rep.add_argument("--out", type=Path, default=None, help="report folder [first RUN_DIR/report]")
    rep.add_argument("--bins", type=int, default=10, help="bins of normalised episode progress [10]")
    rep.add_argument("--resamples", type=int, default=2000, help="bootstrap resamples for the 95%% intervals [2000]")
    rep.add_argument("--workers", type=int, default=None,
                     help="processes measuring runs made before measures were stored [up to 4 above 1 GB of attention]")

    cmp_ = sub.add_parser("compare", help="paired verdict of a candidate run against a baseline run (same seeds)",
                          description="Pair episodes by (task, seed); write compare.json, compare.md and compare.html. "
                                      "Exit 0 pass, 1 REGRESSED or SUSPECT (see --fail-on), 2 incompatible or invalid "
                                      "input, 3 ERRORED (an arm errored on more than half of its paired episodes).")
    cmp_.add_argument("baseline", type=Path, metavar="BASELINE_RUN",
                      help="baseline run folder, or a robustness grid folder (octo-harness robustness): then every "
                           "task x condition is one cell of the Holm family, so one lost condition fails the gate")
    cmp_.add_argument("candidate", type=Path, metavar="CANDIDATE_RUN", help="candidate run (or grid) folder")
    cmp_.add_argument("--max-drop", type=float, default=0.1, help="HELD rules out a larger drop in success rate [0.1]")
    cmp_.add_argument("--alpha", type=float, default=0.05, help="family-wise level; intervals at 1 - alpha [0.05]")
    cmp_.add_argument("--first-steps", type=int, default=10, help="per-step divergence over the first k steps [10]")
    cmp_.add_argument("--fail-on", choices=["regressed", "suspect", "underpowered", "changed"], default="suspect",
                      help="mildest verdict that exits 1: REGRESSED only; also SUSPECT (a drop the interval shows, "
                           "the exact test does not confirm); also UNDERPOWERED; anything but IDENTICAL [suspect]")
    cmp_.add_argument("--out", type=Path, default=None, help="output folder [CANDIDATE_RUN/compare_<baseline name>]")
    cmp_.add_argument("--no-frames", action="store_true", help="do not render step-0 camera frames for the overlays")

    rp = sub.add_parser("replay", help="run a model open loop on the inputs a run recorded (--record-inputs) and "
                                       "compare its actions and attention with the run's",
                        description="The model change isolated from the simulator and the platform: EQUIVALENT (every "
                                    "inferred step within the tolerances) exit 0, CHANGED exit 1, invalid input exit 2.")
    rp.add_argument("run", type=Path, metavar="RUN_DIR", help="a run made with --record-inputs (e.g. a committed baseline)")
    rp.add_argument("--model", default=None, help="the model to replay [the run's own model]")
    rp.add_argument("--action-tolerance", type=float, default=None,
                    help="largest change of an action chunk, in normalised action units [3e-4]")
    rp.add_argument("--attention-tolerance", type=float, default=None,
                    help="largest Jensen-Shannon divergence (bits) of a layer's and head's readout attention [3.5e-7]")
    rp.add_argument("--out", type=Path, default=None, help="output folder for replay.json [RUN_DIR/replay]")

    reg = sub.add_parser("regress", help="run a candidate on a baseline's protocol and seeds until a sequential test decides",
                         description="Pair by pair (round by round over tasks) through the run store (resumable); "
                                     "one anytime-valid test per task (alpha / tasks each); stops as soon as a task "
                                     "regressed or every task decided. Exit codes as for compare, from the worse "
                                     "of the sequential verdict and compare's verdict on the pairs run.")
    reg.add_argument("--baseline", type=Path, required=True, metavar="RUN",
                     help="baseline run folder, or a robustness grid folder: each condition's sequential test then runs "
                          "at alpha / conditions, and the pairs are compared as a grid")
    reg.add_argument("--model", required=True, help="candidate model (as for `run --model`)")
    reg.add_argument("--max-episodes", type=int, default=None, help="at most N episodes per task [the baseline's]")
    reg.add_argument("--max-drop", type=float, default=0.1, help="HELD rules out a larger drop in success rate [0.1]")
    reg.add_argument("--alpha", type=float, default=0.05,
                     help="family-wise level; each task's sequential test runs at alpha / tasks [0.05]")
    reg.add_argument("--out", type=Path, default=Path("results/runs"), help="output root of the candidate run [results/runs]")
    reg.add_argument("--run-name", default=None, help="candidate run folder name [<model>_<protocol hash>]")
    reg.add_argument("--fail-on", choices=["regressed", "suspect", "underpowered", "changed"], default="suspect",
                     help="mildest verdict that exits 1, as for compare; 'changed' also fails a candidate whose numbers "
                          "on the baseline's recorded inputs are not EQUIVALENT (replay): the gate for an unchanged "
                          "model, on any machine [suspect]")
    reg.add_argument("--verbose", action="store_true", default=argparse.SUPPRESS,
                     help="also show other libraries' INFO lines and start-up warnings")
    reg.add_argument("--text-tokenizer", default=None, metavar="auto|fallback|PATH",
                     help="the candidate's text tokenizer (as for `run --text-tokenizer`) [the baseline's choice]")
    _add_execution_args(reg)
    return parser


def _cmd_report(args) -> int:
    from harness.report.build import ReportOptions, build_report

    result = build_report(args.runs, args.out, ReportOptions(bins=args.bins, resamples=args.resamples, workers=args.workers))
    print(f"report: {result.html} ({result.episodes} episodes, {len(result.plots)} plots, {result.seconds:.1f} s)")
    return 0


def _cmd_compare(args) -> int:
    from harness.analysis.compare import CompareConfig, compare_runs, exit_code
    from harness.report.compare_html import step0_frames, write_comparison

    from harness.analysis.compare import compare_grids, is_grid

    config = CompareConfig(max_drop=args.max_drop, alpha=args.alpha, first_steps=args.first_steps)
    if is_grid(args.baseline) != is_grid(args.candidate):
        raise ValueError("compare two robustness grid folders (octo-harness robustness) or two run folders, not one of "
                         "each")
    grid = is_grid(args.baseline)
    result = (compare_grids if grid else compare_runs)(args.baseline, args.candidate, config)
    code = exit_code(result, args.fail_on)
    frames = {} if args.no_frames or result["env"] is None else step0_frames(result, result["env"])
    out = args.out or (args.candidate / f"compare_{args.baseline.resolve().name}" if grid else
                       Path(result["candidate"]["path"]) / f"compare_{result['baseline']['run']}")
    paths = write_comparison(result, out, frames, code)
    print(paths["markdown"].read_text(), end="")
    print(f"compare: {paths['html']}")
    return code


def _cmd_regress(args) -> int:
    from harness.report.compare_html import write_comparison
    from harness.run.regress import exit_code, regress, write_regress

    factory = _execution(args)
    from harness.analysis.compare import is_grid

    if is_grid(args.baseline):  # a robustness grid: condition by condition, Holm over every task x condition
        from harness.run.regress import regress_grid, write_regress_grid

        result = regress_grid(args.baseline, args.model, max_episodes=args.max_episodes, out=args.out,
                              run_name=args.run_name, alpha=args.alpha, max_drop=args.max_drop, executor=factory,
                              text_tokenizer=args.text_tokenizer)
        code = exit_code(result, args.fail_on if args.fail_on != "changed" else "suspect")
        paths = write_regress_grid(result, code, write_comparison)
        print(paths["summary"])
        print(f"regress: {paths['json']}")
        return code
    result = regress(args.baseline, args.model, max_episodes=args.max_episodes, out=args.out, run_name=args.run_name,
                     alpha=args.alpha, max_drop=args.max_drop, executor=factory, text_tokenizer=args.text_tokenizer)
    code = exit_code(result, args.fail_on)
    paths = write_regress(result, code, write_comparison)
    print(paths["summary"])
    print(f"regress: {paths['json']}")
    return code


def _cmd_replay(args) -> int:
    from harness.analysis.equivalence import Tolerances
    from harness.files import atomic_write_json
    from harness.run.replay import exit_code, replay_run, summary_text

    defaults = Tolerances()
    tolerances = Tolerances(action=defaults.action if args.action_tolerance is None else args.action_tolerance,
                            attention_js=defaults.attention_js if args.attention_tolerance is None else args.attention_tolerance)
    result = replay_run(args.run, args.model, tolerances)
    out = args.out or args.run / "replay"
    atomic_write_json(out / "replay.json", result)
    print(summary_text(result))
    print(f"replay: {out / 'replay.json'}")
    return exit_code(result)


def _cmd_robustness(args) -> int:
    from harness.run.robustness import parse_kinds, parse_levels, run_grid
    from harness.run.settings import build_protocol, read_protocol_file

    conditions, levels = parse_kinds(args.perturb), parse_levels(args.levels)
    factory = _execution(args)
    given = {"model": args.model, "task": args.task, "episodes": args.episodes, "seed": args.seed,
             "max_steps": args.max_steps, "fast_render": args.fast_render, "png_every": args.png_every,
             "no_video": args.no_video}
    settings = {**(read_protocol_file(args.protocol) if args.protocol else {}),
                **{k: v for k, v in given.items() if v is not None}}
    if settings.get("perturb"):
        raise ValueError("the grid sets each run's perturbation; drop perturb from the protocol file")
    summaries = run_grid(build_protocol(settings), conditions, levels, args.out, executor=factory,
                         overwrite=args.overwrite)
    for name, summary in summaries.items():
        s = summary.statistics["overall"]
        print(f"{name:<28} {summary.status:<12} {s['successes']}/{s['n']} successes, {s['failed']} errored")
    print(f"robustness: {args.out} (report: octo-harness report {args.out}/*/ --out {args.out}/report)")
    return 0 if all(s.status == "complete" for s in summaries.values()) else 1


def _cmd_tasks() -> int:
    import envs

    print(envs.task_table())
    return 0


RUN_CONTROL = ("protocol", "resume", "overwrite", "retry_failed", "workers", "executor", "ray_address", "policy_replicas")


def _cmd_run(args) -> int:
    from harness.run import ResultsWriteError, RunStore, execute
    from harness.run.schema import protocol_from_manifest
    from harness.run.settings import build_protocol, out_dir, read_protocol_file

    factory = _execution(args)

    given = {k: v for k, v in vars(args).items() if v is not None and k not in ("command", "debug", "verbose", *RUN_CONTROL)}
    if args.resume is not None:
        if given or args.protocol is not None:
            raise ValueError(f"--resume takes the protocol from {args.resume}/manifest.json; drop "
                             + ", ".join("--" + k.replace("_", "-") for k in (given or {"protocol": 1})))
        manifest = RunStore(args.resume).read_manifest()
        if manifest is None:
            raise FileNotFoundError(f"{args.resume} holds no manifest.json; pass the folder of an octo-harness run")
        protocol = protocol_from_manifest(manifest, args.resume / "manifest.json", model_fingerprint=None,
                                          goal_fingerprint=None)
        out, name, method = args.resume.parent, args.resume.name, "wilson"
    else:
        settings = {**(read_protocol_file(args.protocol) if args.protocol else {}), **given}
        protocol = build_protocol(settings)
        out, name, method = out_dir(settings), settings.get("run_name"), settings.get("ci_method", "wilson")
    try:
        summary = execute(protocol, out, name, overwrite=args.overwrite, retry_failed=args.retry_failed, ci_method=method,
                          executor=factory)
    except ResultsWriteError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if summary.skipped:
        print(f"resumed: {summary.skipped} of {len(summary.manifest['jobs'])} episodes were already finished")
    print(summary.table())
    if summary.manifest["model"].get("is_random"):
        print(f"NOTE: {summary.manifest['model']['source']} has random weights; this run checks the pipeline, not Octo's behaviour.")
    print(f"results: {summary.run_dir}")
    return 0 if all(r.status == "ok" for r in summary.rows) else 1


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from harness import console

    console.configure(args.verbose)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None
    try:
        if args.command == "tasks":
            return _cmd_tasks()
        if args.command == "report":
            return _cmd_report(args)
        if args.command == "compare":
            return _cmd_compare(args)
        if args.command == "regress":
            return _cmd_regress(args)
        if args.command == "replay":
            return _cmd_replay(args)
        if args.command == "robustness":
            return _cmd_robustness(args)
        return _cmd_run(args)
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", 2)
        print(f"interrupted ({'SIGTERM' if signum == 15 else 'SIGINT'}); finished episodes are recorded, "
              "run the same command to resume", file=sys.stderr)
        return 128 + signum
    except _user_errors() as exc:
        if args.debug:
            raise
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"error: {message}", file=sys.stderr)
        return 2
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


if __name__ == "__main__":
    sys.exit(main())

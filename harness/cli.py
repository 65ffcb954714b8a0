"""Command line: `octo-harness run ...` (closed-loop evaluation with attention capture) and `octo-harness tasks`.

Only parses arguments into frozen configs, wires the runner and prints; user errors are one line.
"""

from __future__ import annotations

import argparse
import errno
import signal
import sys
import threading
from pathlib import Path

USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, KeyError, FileNotFoundError, PermissionError)
# An unexpected exception in any command (a bug): its own code, never 1 (a verdict for compare and regress, "an episode
# failed" for run) nor 2 (bad input). docs/running.md#exit-codes
INTERNAL_ERROR = 5
DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)  # a write the disk refused


def _user_errors() -> tuple[type[BaseException], ...]:
    from envs.gl import HeadlessGLError
    from envs.libero_env import LiberoServerError
    from harness.octo.errors import OctoError
    from harness.run.store import ResultsWriteError, RunLockedError

    # ResultsWriteError: a full disk under regress's candidate run is exit 2, never 1 (REGRESSED)
    return (*USER_ERRORS, RunLockedError, OctoError, HeadlessGLError, OutputsNotWritten, ResultsWriteError,
            LiberoServerError)


def _interrupt(signum, frame):
    """SIGINT / SIGTERM before the run installs its own handler (loading the model, compiling): the same exit as
    later, recorded first so a KeyboardInterrupt swallowed by a finaliser is not lost (harness.interrupts)."""
    from harness import interrupts

    interrupts.handler(signum, frame)


def _video_attention(text: str):
    from harness.outputs.writers import ATTRIBUTION_VIDEO

    if text in ("rollout", *ATTRIBUTION_VIDEO):
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--video-attention takes a layer index, 'rollout' or one of "
                                         f"{', '.join(ATTRIBUTION_VIDEO)}, got {text!r}") from None


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        port = None
    if port is None or not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"takes a port number 1-65535, got {text[:40]!r}")
    return port


def _render_device(text: str) -> str:
    value = text.strip().lower()
    if value in ("cpu", "gpu") or value.isdigit():
        return value
    raise argparse.ArgumentTypeError(f"--render-device takes cpu, gpu or an EGL device number, got {text!r}")


def _add_render_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--render-device", type=_render_device, default=None, metavar="cpu|gpu|N",
                        help="where MuJoCo renders, whatever device JAX computes on: cpu (Mesa llvmpipe: the safe choice "
                             "when JAX uses the GPU), gpu (EGL on the first GPU) or N (EGL device N); recorded in the "
                             "manifest's platform.gl [MuJoCo's choice]")


def _apply_render_device(choice: str | None) -> None:
    """Before anything imports MuJoCo: OCTO_HARNESS_RENDER_DEVICE for envs.gl (worker processes inherit it); a
    device that cannot be set up is one line (HeadlessGLError, exit 2)."""
    if choice is None:
        return
    import os

    if "envs" in sys.modules:  # already configured (an in-process caller): configure again with the choice
        os.environ["OCTO_HARNESS_RENDER_DEVICE"] = choice
        from envs import gl

        gl.configure()
    else:
        os.environ["OCTO_HARNESS_RENDER_DEVICE"] = choice
        from envs import gl
    if gl.render_device_error is not None:
        raise gl.HeadlessGLError(gl.render_device_error)


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


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors as one line naming the option and the fix (exit 2), not a usage block."""

    FIXES = (("invalid int value", "pass a whole number"), ("invalid float value", "pass a number"),
             ("invalid choice", "pick one of the choices listed"), ("expected one argument", "give it a value"),
             ("required", "add them"), ("unrecognized arguments", "drop them or check the spelling"))

    def error(self, message: str):
        fix = next((fix for text, fix in self.FIXES if text in message), "fix that option")
        self.exit(2, f"error: {self.prog}: {_one_line(message.splitlines()[0] if message else message, 300)}; {fix} "
                     f"(see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="octo-harness", description=__doc__.splitlines()[0])
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
    r.add_argument("--video-cameras", default=None, metavar="KEYS",
                   help="cameras shown in the MP4, one row each (frame | overlay), e.g. image_primary or "
                        "image_primary,image_wrist [all: every camera the model reads]")
    r.add_argument("--overlay-interpolation", choices=["nearest", "bilinear"], default=None,
                   help="how patch-grid maps are enlarged in PNGs, MP4 and recording: nearest (the honest patch grid) "
                        "or bilinear (smooth, as the original attention-visualisation scripts) [nearest]")
    r.add_argument("--rerun", default=None, metavar="save|spawn|serve",
                   help="Rerun recording of every episode (pip install 'octo-harness[viewer]'): save writes "
                        "episode.rrd beside its files (part of the protocol); spawn streams live to a viewer on this "
                        "machine; serve hosts the web viewer for a headless server and prints its URL once "
                        "(save,spawn / save,serve: both); see docs/viewer.md")
    r.add_argument("--viewer-port", type=_port, default=None, metavar="PORT",
                   help="--rerun spawn/serve: the viewer's gRPC port [9876]; serve's web viewer uses --web-port")
    r.add_argument("--web-port", type=_port, default=None, metavar="PORT", help="--rerun serve: the web viewer's HTTP port [9090]")
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
    r.add_argument("--image-convention", choices=["upright", "opengl", "rot180"], default=None,
                   help="orientation of the frames the model was trained on (rot180: OpenVLA's LIBERO datasets) [upright]")
    r.add_argument("--action-space", choices=["octo-delta", "robosuite", "libero"], default=None,
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
    r.add_argument("--faithfulness-fill", choices=["mean", "blur", "impute"], default=None,
                   help="what a deleted patch becomes in the faithfulness curves: the frame's mean colour, a blur of "
                        "the frame, or noisy linear imputation from the surrounding pixels (ROAD; in distribution, "
                        "no shape leak) [mean]")
    r.add_argument("--attention-controls", default=None, metavar="blank,mirror",
                   help="position-against-content controls: ask the model each control step again with every camera's "
                        "frames blanked to their mean colour and/or mirrored left-right; attention in controls.npz "
                        "(docs/phases-and-position.md)")
    r.add_argument("--controls-every", type=int, default=None, metavar="N",
                   help="run the attention controls at every N-th inference step [1 with --attention-controls]")
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
    _add_render_arg(r)

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
    rep.add_argument("--margin", type=float, default=0.15,
                     help="a robustness cell HOLDS when its drop's upper confidence bound is below this [0.15]")
    rep.add_argument("--workers", type=int, default=None,
                     help="processes measuring runs made before measures were stored [up to 4 above 1 GB of attention]")

    cmp_ = sub.add_parser("compare", help="paired verdict of a candidate run against a baseline run (same seeds)",
                          description="Pair episodes by (task, seed); write compare.json, compare.md and compare.html. "
                                      "Exit 0 pass, 1 REGRESSED or SUSPECT (see --fail-on), 2 incompatible or invalid "
                                      "input, or outputs that could not be written, 3 ERRORED (an arm errored on more "
                                      "than half of its paired episodes), 4 INCOMPLETE (the candidate lacks episodes "
                                      "the baseline finished).")
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
    _add_render_arg(cmp_)

    rp = sub.add_parser("replay", help="run a model open loop on the inputs a run recorded (--record-inputs) and "
                                       "compare its actions and attention with the run's",
                        description="The model change isolated from the simulator and the platform: EQUIVALENT (every "
                                    "inferred step within the tolerances) exit 0, CHANGED exit 1, invalid input or "
                                    "replay.json not written exit 2.")
    rp.add_argument("run", type=Path, metavar="RUN_DIR", help="a run made with --record-inputs (e.g. a committed baseline)")
    rp.add_argument("--model", default=None, help="the model to replay [the run's own model]")
    rp.add_argument("--action-tolerance", type=float, default=None,
                    help="largest change of an action chunk, in normalised action units [3e-4]")
    rp.add_argument("--attention-tolerance", type=float, default=None,
                    help="largest Jensen-Shannon divergence (bits) of a layer's and head's readout attention [3.5e-7]")
    rp.add_argument("--out", type=Path, default=None, help="output folder for replay.json [RUN_DIR/replay]")

    vw = sub.add_parser("view", help="open an episode of a finished run in the Rerun viewer (pip install 'octo-harness[viewer]')",
                        description="Scrub one episode: frames, every layer's and head's attention, attribution maps, "
                                    "actions, rewards and measures on one timeline. A run made with --rerun save is "
                                    "opened as recorded; otherwise the recording is rebuilt from the run's files and the "
                                    "frames re-simulated from the episode's seed (checked bit for bit against the "
                                    "recorded actions). See docs/viewer.md.")
    vw.add_argument("run", type=Path, metavar="RUN_DIR")
    vw.add_argument("--task", default=None, help="task of the episode [the run's first]")
    vw.add_argument("--episode", type=int, default=None, help="episode index within the task [the first finished]")
    vw.add_argument("--save", type=Path, default=None, metavar="PATH",
                    help="write the recording to PATH (.rrd; open later with `rerun PATH`) instead of opening a viewer")
    vw.add_argument("--serve", action="store_true",
                    help="serve the web viewer from this machine (a headless server) and print its URL; Ctrl-C stops it")
    vw.add_argument("--no-simulate", action="store_true",
                    help="do not re-simulate the episode for its frames: maps and measures only")
    vw.add_argument("--viewer-port", type=_port, default=None, metavar="PORT", help="the viewer's gRPC port [9876]")
    vw.add_argument("--web-port", type=_port, default=None, metavar="PORT", help="--serve: the web viewer's HTTP port [9090]")

    san = sub.add_parser("sanity", help="sanity checks of the attribution methods, once per policy: model-parameter "
                                         "randomisation and patch additivity, open loop on recorded inputs",
                         description="On the inputs of runs made with --record-inputs: Spearman and SSIM between the "
                                     "maps of the trained policy and of the policy with re-drawn weights (cascading "
                                     "from the top block down, and each block alone), per method and camera, with "
                                     "95%% intervals over steps and a pass/fail verdict; with --additivity also "
                                     "single-patch effects and their additivity per camera and fill. Writes "
                                     "sanity.json, randomisation.csv, additivity.csv; prints Markdown tables.")
    san.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR", help="run folder(s) made with --record-inputs "
                                                                           "(one policy; several tasks pool)")
    san.add_argument("--model", default=None, help="the policy to check [the runs' own model]")
    san.add_argument("--every", type=int, default=10, help="every k-th inferred step of each episode [10]")
    san.add_argument("--max-steps", type=int, default=None, help="at most N steps in all [every selected step]")
    san.add_argument("--methods", default=None,
                     help="attribution methods (as for run --attribution; random is always added) "
                          "[attention,rollout,grad-attention,saliency,occlusion]")
    san.add_argument("--additivity", action="store_true",
                     help="also measure single-patch effects and how additive they are, per camera and fill")
    san.add_argument("--fills", default=None, help="fills of the additivity measures, comma-separated [mean,blur,impute]")
    san.add_argument("--seed", type=int, default=0, help="seed of the re-drawn weights and the random orders [0]")
    san.add_argument("--out", type=Path, default=None, help="output folder [first RUN_DIR/sanity]")

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
    _add_render_arg(reg)
    return parser


class OutputsNotWritten(RuntimeError):
    """A gate's verdict was reached but its output files could not be written (exit 2: never read as a verdict)."""


def _writing(what: str, verdict: str, write):
    """`write()`, or OutputsNotWritten (one line, exit 2) when the disk refuses (full, read-only, permissions): exit 1
    would read as REGRESSED / CHANGED."""
    try:
        return write()
    except OSError as exc:
        reason = exc.strerror or str(exc).splitlines()[0] or type(exc).__name__
        raise OutputsNotWritten(f"could not write {what}: {reason}; the verdict was {verdict}, but without its files "
                                "it does not count: free space or pass --out on another disk, then run it again") from None


def _cmd_report(args) -> int:
    from harness.report.build import ReportOptions, build_report

    result = build_report(args.runs, args.out, ReportOptions(bins=args.bins, resamples=args.resamples, workers=args.workers,
                                                                  margin=args.margin))
    print(f"report: {result.html} ({result.episodes} episodes, {len(result.plots)} plots, {result.seconds:.1f} s)")
    return 0


def _cmd_compare(args) -> int:
    from harness.analysis.compare import CompareConfig, compare_grids, compare_runs, exit_code, is_grid
    from harness.report.compare_html import step0_frames, write_comparison

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
    paths = _writing(f"compare's outputs in {out}", result["verdict"], lambda: write_comparison(result, out, frames, code))
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
    paths = _writing(f"regress's outputs in {result['candidate_run']}/regress", result["verdict"],
                     lambda: write_regress(result, code, write_comparison))
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
    _writing(f"{out / 'replay.json'}", result["verdict"], lambda: atomic_write_json(out / "replay.json", result))
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


def _cmd_sanity(args) -> int:
    from harness.run.sanity import DEFAULT_METHODS, SanityOptions, markdown, run_sanity

    fills = tuple(f.strip() for f in args.fills.split(",") if f.strip()) if args.fills else SanityOptions.fills
    options = SanityOptions(every=args.every, methods=args.methods or DEFAULT_METHODS, additivity=args.additivity,
                            fills=fills, seed=args.seed, max_steps=args.max_steps)
    out = args.out or args.runs[0] / "sanity"
    result = run_sanity(args.runs, out, options, model_source=args.model)
    print(markdown(result))
    print(f"sanity: {out / 'sanity.json'} ({result['steps']} steps, {result['seconds']:.0f} s)")
    return 0


def _cmd_view(args) -> int:
    import tempfile

    from harness.outputs.rerun_sink import import_rerun
    from harness.outputs.rerun_viewer import check_viewer, serve_file, start_viewer
    from harness.run.view import build_recording

    rr = import_rerun()
    if args.save is not None and args.save.suffix != ".rrd":
        raise ValueError(f"--save {args.save}: a Rerun recording's name ends in .rrd")
    if args.serve or args.save is None:  # before the episode is rebuilt: no display, a port out of range or in use
        check_viewer("serve" if args.serve else "spawn", args.viewer_port, args.web_port)
    simulate = not args.no_simulate
    if args.save is not None or args.serve:
        with tempfile.TemporaryDirectory() as scratch:
            target = args.save or Path(scratch) / "episode.rrd"
            result = build_recording(args.run, args.task, args.episode, save=target, simulate=simulate)
            print(f"{result.episode.task} episode {result.episode.episode}: frames: {result.frames}")
            if args.save is not None:
                print(f"recording: {result.path}  (open it with: rerun {result.path})")
            if args.serve:
                viewer = serve_file(result.path, args.viewer_port, args.web_port)
                _keep_serving(viewer, f"Rerun web viewer: {viewer.web_url}")
        return 0
    viewer = start_viewer("spawn", args.viewer_port)
    result = build_recording(args.run, args.task, args.episode, connect=viewer.url, simulate=simulate)
    if result.source == "recording":
        stream = rr.RecordingStream("octo-harness", recording_id=f"file:{result.path}")
        stream.connect_grpc(viewer.url)
        stream.log_file_from_path(result.path)
        stream.flush(blocking=True)
    print(f"{result.episode.task} episode {result.episode.episode} sent to the viewer; frames: {result.frames}")
    return 0


def _cmd_tasks() -> int:
    import envs

    print(envs.task_table(libero=True))
    return 0


RUN_CONTROL = ("protocol", "resume", "overwrite", "retry_failed", "workers", "executor", "ray_address", "policy_replicas",
               "render_device", "viewer_port", "web_port")


def _live_viewer(args, modes: tuple[str, ...]):
    """--rerun modes -> the live viewer started for spawn / serve, or None. A missing viewer extra is one line."""
    from harness.outputs.rerun_sink import import_rerun
    from harness.outputs.rerun_viewer import start_viewer

    if (args.viewer_port is not None or args.web_port is not None) and not {"spawn", "serve"} & set(modes):
        raise ValueError("--viewer-port and --web-port need --rerun spawn or --rerun serve")
    if modes:
        import_rerun()
    live = next((m for m in modes if m in ("spawn", "serve")), None)
    if live is None:
        return None
    viewer = start_viewer(live, args.viewer_port, args.web_port)
    if live == "serve":
        print(f"Rerun web viewer: {viewer.web_url}  (on a remote server: ssh -L {args.web_port or 9090}:localhost:"
              f"{args.web_port or 9090} -L {args.viewer_port or 9876}:localhost:{args.viewer_port or 9876} <server>)",
              flush=True)
    else:
        print(f"Rerun viewer spawned; episodes stream to {viewer.url}", flush=True)
    return viewer


def _cmd_run(args) -> int:
    from harness.run import ResultsWriteError, RunStore, execute
    from harness.run.protocol import protocol_from_manifest
    from harness.run.settings import build_protocol, out_dir, read_protocol_file

    factory = _execution(args)
    from harness.outputs.rerun_sink import parse_modes

    modes = parse_modes(args.rerun)  # a bad --rerun is one line, before anything heavy
    given = {k: v for k, v in vars(args).items() if v is not None and k not in ("command", "debug", "verbose", "rerun",
                                                                                   *RUN_CONTROL)}
    if "save" in modes:
        given["rerun"] = True  # an output option of the protocol (spawn and serve are not)
    if args.resume is not None:
        if given or args.protocol is not None:
            raise ValueError(f"--resume takes the protocol from {args.resume}/manifest.json; drop "
                             + ", ".join("--" + k.replace("_", "-") for k in (given or {"protocol": 1})))
        manifest = RunStore(args.resume).read_manifest()
        if manifest is None:
            raise FileNotFoundError(f"{args.resume} holds no manifest.json; pass the folder of an octo-harness run")
        protocol = protocol_from_manifest(manifest, args.resume / "manifest.json", model_fingerprint=None,
                                          goal_fingerprint=None)
        out, name, method = args.resume.parent, args.resume.name, None  # the manifest's statistics.ci_method
    else:
        settings = {**(read_protocol_file(args.protocol) if args.protocol else {}), **given}
        protocol = build_protocol(settings)
        out, name, method = out_dir(settings), settings.get("run_name"), settings.get("ci_method")
    viewer = _live_viewer(args, modes)
    try:
        summary = execute(protocol, out, name, overwrite=args.overwrite, retry_failed=args.retry_failed, ci_method=method,
                          executor=factory, viewer=viewer.url if viewer is not None else None)
    except ResultsWriteError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if summary.skipped:
        print(f"resumed: {summary.skipped} of {len(summary.manifest['jobs'])} episodes were already finished")
    print(summary.table())
    if summary.manifest["model"].get("is_random"):
        print(f"NOTE: {summary.manifest['model']['source']} has random weights; this run checks the pipeline, not Octo's behaviour.")
    print(f"results: {summary.run_dir}")
    code = 0 if all(r.status == "ok" for r in summary.rows) else 1
    if viewer is not None and viewer.mode == "serve":
        _keep_serving(viewer, "run finished; the web viewer keeps serving its recordings")
    return code


def _keep_serving(viewer, what: str = "the web viewer keeps serving") -> None:
    """The web viewer lives in this process: keep it until Ctrl-C (as `rerun --serve-web` does)."""
    import time

    print(f"{what}; Ctrl-C to stop", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:  # the way to stop serving, not an interruption of the command
        from harness import interrupts

        interrupts.reset()


ECHO_LIMIT = 1000  # characters of one error line: a value echoed from a 50 MB input is cut, with its length said


def _one_line(message, limit: int = ECHO_LIMIT) -> str:
    """An error's text as one line, cut to `limit` characters (a 50 MB bad value never floods the terminal)."""
    text = " ".join(str(message).splitlines())
    return text if len(text) <= limit else f"{text[:limit - 40]}... (cut: {len(text)} characters in all)"


def _origin(exc: BaseException) -> str:
    """ ' (at module.py:123)' of the innermost frame that raised, for a bug report."""
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return f" (at {Path(tb.tb_frame.f_code.co_filename).name}:{tb.tb_lineno})" if tb is not None else ""


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from harness import console

    console.configure(args.verbose)
    from harness import interrupts

    interrupts.reset()
    main_thread = threading.current_thread() is threading.main_thread()
    previous = {s: signal.signal(s, _interrupt) for s in (signal.SIGINT, signal.SIGTERM)} if main_thread else {}
    try:
        code = _dispatch(args)
        interrupts.check()  # a signal whose KeyboardInterrupt a finaliser swallowed: still 128 + signum
        return code
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", 2)
        print(f"interrupted ({'SIGTERM' if signum == 15 else 'SIGINT'}); finished episodes are recorded, "
              "run the same command to resume", file=sys.stderr)
        return 128 + signum
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)


def _dispatch(args) -> int:
    """The command, its errors as exit codes: 2 for bad input or a full disk, INTERNAL_ERROR for a bug."""
    try:
        _apply_render_device(getattr(args, "render_device", None))
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
        if args.command == "view":
            return _cmd_view(args)
        if args.command == "sanity":
            return _cmd_sanity(args)
        if args.command == "robustness":
            return _cmd_robustness(args)
        return _cmd_run(args)
    except _user_errors() as exc:
        if args.debug:
            raise
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"error: {_one_line(message)}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a read-only filesystem, a quota: one line (exit 2), never a verdict
        if exc.errno not in DISK_ERRORS:
            return _internal_error(exc, args)
        if args.debug:
            raise
        where = f" {exc.filename}" if exc.filename else " its outputs"
        print(f"error: could not write{where}: {exc.strerror or exc}; free space (or pass --out on another disk) and "
              f"run the same command again", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - the one place a bug becomes an exit code that is no verdict
        return _internal_error(exc, args)


def _internal_error(exc: BaseException, args) -> int:
    """A bug: one line saying so (the traceback with --debug), exit INTERNAL_ERROR."""
    if args.debug:
        import traceback

        traceback.print_exception(exc)
    where = _origin(exc)
    print(f"internal error: {type(exc).__name__}: {_one_line(exc, 300)}{where}; please report it (run with "
          f"octo-harness --debug {args.command} ... for the traceback); exit {INTERNAL_ERROR}", file=sys.stderr)
    return INTERNAL_ERROR


if __name__ == "__main__":
    sys.exit(main())

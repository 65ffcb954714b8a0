"""Command line: `octo-harness run ...` (closed-loop evaluation with attention capture) and `octo-harness tasks`.

Only parses arguments into frozen configs, wires the runner and prints; user errors are one line.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, KeyError, FileNotFoundError, PermissionError)


def _parse_layers(text: str | None) -> tuple[int, ...] | None:
    if not text or text == "all":
        return None
    try:
        return tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--layers takes comma-separated layer indices or 'all', got {text!r}") from None


def _video_attention(text: str):
    if text == "rollout":
        return "rollout"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--video-attention takes 'rollout' or a layer index, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="octo-harness", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show tracebacks for errors")
    sub = parser.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run closed-loop episodes and record attention")
    r.add_argument("--task", action="append", required=True,
                   help="task name (repeat or comma-separate for several; 'all' for every registered task)")
    r.add_argument("--episodes", type=int, default=1)
    r.add_argument("--model", default="hf://rail-berkeley/octo-small-1.5",
                   help="hf://owner/name, a local checkpoint folder, or random:octo-small-1.5 / random:octo-base-1.5")
    r.add_argument("--max-steps", type=int, default=None, help="stop each episode after N control steps")
    r.add_argument("--out", type=Path, default=Path("results/runs"), help="output root (default results/runs)")
    r.add_argument("--run-name", default=None, help="folder name of this run (default: UTC time + model)")
    r.add_argument("--seed", type=int, default=0, help="episode k uses seed + k")
    r.add_argument("--instruction", default=None, help="override the task's language instruction")
    r.add_argument("--dataset-key", default=None,
                   help="dataset statistics used to unnormalise actions (default: bridge_dataset when present)")
    r.add_argument("--execution", choices=["temporal_ensemble", "receding_horizon"], default="temporal_ensemble")
    r.add_argument("--receding-steps", type=int, default=4, help="actions executed per inference (receding horizon)")
    r.add_argument("--ensemble-weight", type=float, default=0.0, help="temporal ensemble weight exp(-w*i); 0 = mean")
    r.add_argument("--png-every", type=int, default=1, help="write overlays every n-th step (0 = none)")
    r.add_argument("--layers", type=_parse_layers, default=None, help="overlay layers, e.g. 0,5,11 (default all)")
    r.add_argument("--video-attention", type=_video_attention, default=-1,
                   help="attention shown in the MP4: a layer index (default -1 = last) or 'rollout'")
    r.add_argument("--normalisation", choices=["frame", "episode"], default="frame")
    r.add_argument("--no-video", action="store_true")
    r.add_argument("--gif", action="store_true", help="also write rollout.gif")
    r.add_argument("--bbox", action="store_true", help="draw the target object's bounding box on overlays")
    r.add_argument("--no-masks", action="store_true", help="do not render target/robot masks")
    r.add_argument("--goal-images", type=Path, default=None,
                   help="folder with <obs key>.png goal images (image_primary.png, ...) for goal-conditioned models")
    r.add_argument("--fast-render", action="store_true",
                   help="render without reflections, shadows and anti-aliasing (~3.6x faster frames)")

    sub.add_parser("tasks", help="list the registered tasks")
    return parser


def _cmd_tasks() -> int:
    import envs

    print(envs.task_table())
    return 0


def _expand_tasks(values: list[str]) -> tuple[str, ...]:
    import envs

    names = [t.strip() for v in values for t in v.split(",") if t.strip()]
    if names == ["all"]:
        return tuple(spec.name for spec in envs.list_tasks())
    return tuple(names)


def _cmd_run(args) -> int:
    from harness.policy import PolicyConfig
    from harness.runner import RunConfig, run
    from harness.writers import OutputOptions

    outputs = OutputOptions(
        png_every=args.png_every,
        layers=args.layers,
        video=not args.no_video,
        video_attention=args.video_attention,
        gif=args.gif,
        normalisation=args.normalisation,
        bbox=args.bbox,
    )
    policy = PolicyConfig(
        execution=args.execution,
        receding_steps=args.receding_steps,
        ensemble_weight=args.ensemble_weight,
        dataset_key=args.dataset_key,
        full_attention=args.video_attention == "rollout",
    )
    config = RunConfig(
        tasks=_expand_tasks(args.task),
        model=args.model,
        episodes=args.episodes,
        seed=args.seed,
        max_steps=args.max_steps,
        out_dir=args.out,
        run_name=args.run_name,
        instruction=args.instruction,
        masks=not args.no_masks,
        fast_render=args.fast_render,
        goal_images=args.goal_images,
        policy=policy,
        outputs=outputs,
    )
    progress = _Progress(args.episodes, args.max_steps)
    summary = run(config, on_step=progress)
    progress.close()
    print(summary.table())
    if summary.manifest.get("model_is_random"):
        print(f"NOTE: {summary.manifest['model']} has random weights; this run checks the pipeline, not Octo's behaviour.")
    print(f"results: {summary.run_dir}")
    return 0 if all(r.status == "ok" for r in summary.rows) else 1


class _Progress:
    """One-line progress bar on stderr (a line every 25 steps when stderr is not a terminal)."""

    def __init__(self, episodes: int, max_steps: int | None):
        self.episodes, self.max_steps = episodes, max_steps
        self.tty = sys.stderr.isatty()
        self.start = time.perf_counter()

    def __call__(self, task, episode, t, record) -> None:
        total = f"/{self.max_steps}" if self.max_steps else ""
        line = (f"{task} episode {episode + 1}/{self.episodes} step {t + 1}{total} "
                f"success={record.success} {time.perf_counter() - self.start:6.1f}s")
        if self.tty:
            sys.stderr.write("\r" + line.ljust(79))
            sys.stderr.flush()
        elif (t + 1) % 25 == 0 or t == 0:
            print(line, file=sys.stderr)

    def close(self) -> None:
        if self.tty:
            sys.stderr.write("\n")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")
    try:
        if args.command == "tasks":
            return _cmd_tasks()
        return _cmd_run(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except USER_ERRORS as exc:
        if args.debug:
            raise
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

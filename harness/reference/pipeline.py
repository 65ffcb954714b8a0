"""One command that builds the reference policy: record demonstrations, then train and save the model.

    python -m harness.reference.pipeline --out models/octo-reference-robosuite --data data/reference_demos

Everything is seeded (demonstration seeds, batch sampling, initialisation, noise), so the same command on
the same software gives the same demonstrations and the same training run. A recording that already
exists in `--data` with the same configuration is reused (its recording time is reported from its summary).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import replace
from pathlib import Path

from harness.reference.demos import DemoConfig, existing_demos, load_demos, record_demos
from harness.reference.train import TrainConfig, train

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m harness.reference.pipeline", description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="models/octo-reference-robosuite", help="checkpoint folder to write")
    parser.add_argument("--data", default="data/reference_demos", help="folder for the recorded demonstrations (not committed)")
    parser.add_argument("--episodes", type=int, default=None,
                        help="demonstrations per task, the same for every task [Lift 96, Stack 128, PickPlaceCan 192]")
    parser.add_argument("--steps", type=int, default=TrainConfig.steps, help="training steps")
    parser.add_argument("--batch-size", type=int, default=TrainConfig.batch_size)
    parser.add_argument("--workers", type=int, default=2, help="recording processes (spawned)")
    parser.add_argument("--seed", type=int, default=TrainConfig.seed, help="training seed")
    parser.add_argument("--init-from", default=None, metavar="CHECKPOINT",
                        help="warm start from this checkpoint folder (same architecture; patch-grid position embeddings "
                             "are resampled to the new image sizes) instead of random initialisation")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    for noisy in ("jax._src.xla_bridge", "robosuite_logs"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    if (args.episodes is not None and args.episodes < 4) or args.steps < 1 or args.batch_size < 1:
        parser.error("--episodes must be >= 4 (one per recording job), --steps and --batch-size >= 1")

    start = time.perf_counter()
    train_config = TrainConfig(steps=args.steps, batch_size=args.batch_size, seed=args.seed, init_from=args.init_from)
    demo_config = DemoConfig(image_sizes=train_config.image_sizes)
    if args.episodes is not None:
        demo_config = replace(demo_config, episodes=tuple((t, args.episodes) for t in demo_config.tasks))
    summary = existing_demos(demo_config, args.data)
    if summary is None:
        log.info("recording %s demonstrations into %s", dict(demo_config.episodes), args.data)
        summary = record_demos(demo_config, args.data, workers=args.workers)
    else:
        log.info("reusing the demonstrations in %s (recorded in %.0f s)", args.data, summary["seconds"])
    result = train(load_demos(args.data, demo_config.tasks), args.out, train_config)
    result["demonstrations"] = summary
    result["pipeline_seconds_this_run"] = time.perf_counter() - start
    Path(args.out, "training_summary.json").write_text(json.dumps(result, indent=2, default=str))
    log.info("done: %s (demonstrations %.0f s, training %.0f s)", args.out, summary["seconds"], result["total_seconds"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

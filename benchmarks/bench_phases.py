"""What task phases, the gripper/arm/goal masks and the attention controls cost (docs/phases-and-position.md).

Env side, per control step of a task (default Stack and PickPlaceCan, the default cameras, fast render): the
phase function (`env.phase()`: robosuite's grasp check and a few positions), and the masks of every camera with
the new categories (`env.masks()`: target, robot, gripper, arm, goal) against the same segmentation renders
split only into target and robot (what a step paid before). All timed round-robin (interleaved medians), on
one env after a reset and a few steps.

Policy side: one inference of the reference policy (the policy's inference, batch 1, as a run calls it) without controls
and with `--attention-controls blank,mirror` at a control step (two more forward passes), so the added time per
step with `--controls-every N` is (controlled - plain) / N.

    .venv/bin/python benchmarks/bench_phases.py [--tasks Stack,PickPlaceCan] [--model models/octo-reference-robosuite]
        [--reps 30]
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from bench_faithfulness import request  # noqa: E402
from bench_octo import interleaved_medians  # noqa: E402
import envs  # noqa: E402
from envs.segmentation import masks_from_segmentation, scene_lookup  # noqa: E402
from harness.policies import load_policy  # noqa: E402
from harness.policy import PolicyConfig  # noqa: E402


def env_costs(task: str, reps: int) -> dict[str, float]:
    env = envs.make(task, masks=True, fast_render=True)
    inner = env.unwrapped
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.zeros(env.action_space.shape, np.float32))

    def old_masks():  # the same renders, split into target and robot only (as before this feature)
        for spec in inner.config.cameras:
            image, segids, objtypes, objids = inner._renderer.segmentation(spec.key)
            masks_from_segmentation(image, scene_lookup(segids, objtypes, objids, inner._geom_category))

    try:
        step = np.zeros(env.action_space.shape, np.float32)
        return interleaved_medians({"phase": inner.phase, "masks": inner.masks, "masks_old": old_masks,
                                    "step": lambda: env.step(step)}, reps)
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="Stack,PickPlaceCan")
    parser.add_argument("--model", default="models/octo-reference-robosuite")
    parser.add_argument("--reps", type=int, default=30)
    args = parser.parse_args()
    print(f"{'task':<14} {'env step s':>10} {'phase ms':>9} {'masks ms':>9} {'masks before ms':>15} {'added/step':>10}")
    for task in args.tasks.split(","):
        t = env_costs(task, args.reps)
        added = t["phase"] + t["masks"] - t["masks_old"]
        print(f"{task:<14} {t['step']:>10.4f} {1e3 * t['phase']:>9.3f} {1e3 * t['masks']:>9.3f} "
              f"{1e3 * t['masks_old']:>15.3f} {added / t['step']:>9.1%}")
    model = load_policy(args.model)
    req = request(model)
    plain = model.inference(PolicyConfig())
    controlled = model.inference(PolicyConfig(attention_controls="blank,mirror"))
    t = interleaved_medians({"plain": lambda: plain([req]), "controls": lambda: controlled([req])}, args.reps)
    print(f"\n{args.model}: inference {1e3 * t['plain']:.2f} ms, with blank+mirror controls {1e3 * t['controls']:.2f} ms "
          f"({t['controls'] / t['plain']:.2f}x; added per control step {1e3 * (t['controls'] - t['plain']):.2f} ms)")


if __name__ == "__main__":
    main()

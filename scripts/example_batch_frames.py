"""Rewrite a reference checkpoint's example_batch.msgpack from one scripted demonstration (its weights unchanged).

Octo's finetuning writes the batch it built the model from, so a finetune's example frames are real training frames.
The reference pipelines wrote zeros; this gives the committed checkpoints the same evidence: the middle frame of one
expert demonstration per camera (at the checkpoint's training size and orientation), its proprio, the first action
chunk from there and the task's instruction. The demonstration is recorded with the reference package's own
recorders (reference_policies.demos / libero_demos), from a training seed of a task the known-answer tests do not use.

    .venv/bin/python scripts/example_batch_frames.py --family robosuite models/octo-reference-robosuite \
        models/octo-reference-robosuite-64px
    .venv/bin/python scripts/example_batch_frames.py --family libero models/octo-reference-libero-object \
        models/octo-reference-libero-object-first

Prints one JSON line: where the frame came from (the checkpoint's model card quotes it).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

ROBOSUITE_TASK = "Stack"  # the known-answer tests render Lift (evaluation seed 0)
LIBERO_TASK = "libero_object/5"  # the known-answer tests render libero_object/0 (stored state 0)


def _robosuite_demo() -> tuple[dict, dict]:
    import envs
    from reference_policies.demos import DemoConfig, record_episode, successful_episodes
    from reference_policies.experts import ScriptedExpert

    config = DemoConfig()
    native = {"image_primary": 256, "image_wrist": 128}  # the env's default cameras; resized per checkpoint below
    env = envs.make(ROBOSUITE_TASK, fast_render=config.fast_render, action_space="robosuite",
                    max_episode_steps=config.max_steps[ROBOSUITE_TASK])
    try:
        expert = ScriptedExpert(ROBOSUITE_TASK, config.expert)
        first = config.task_seed_base(ROBOSUITE_TASK)
        (episode,), (seed,), _ = successful_episodes(
            lambda s: record_episode(env, expert, s, native, config.noise, config.max_steps[ROBOSUITE_TASK]),
            ROBOSUITE_TASK, first, 1)
    finally:
        env.close()
    return episode, {"task": ROBOSUITE_TASK, "seed": seed, "convention": "upright", "rendered": native,
                     "recorder": "reference_policies.demos.record_episode (DemoConfig defaults, noise 0.3)"}


def _libero_demo() -> tuple[dict, dict]:
    from envs.libero_tasks import get_libero_task
    from reference_policies.demos import successful_episodes
    from reference_policies.libero_demos import LiberoDemoConfig, make_env, record_episode

    config = LiberoDemoConfig()
    env = make_env(LIBERO_TASK, config)
    try:
        target = get_libero_task(LIBERO_TASK).targets[0]
        first = config.task_seed_base(LIBERO_TASK)
        (episode,), (seed,), _ = successful_episodes(lambda s: record_episode(env, target, s, config), LIBERO_TASK,
                                                     first, 1)
    finally:
        env.close()
    return episode, {"task": LIBERO_TASK, "seed": seed, "convention": config.image_convention,
                     "rendered": {k: s for k, _, s in config.cameras},
                     "recorder": "reference_policies.libero_demos.record_episode (LiberoDemoConfig defaults)"}


def _instruction(family: str, task: str) -> str:
    if family == "libero":
        from envs.libero_tasks import get_libero_task

        return get_libero_task(task).instruction
    from envs.resolver import get_task

    return get_task(task).instruction


def rewrite(folder: Path, family: str, episode: dict, source: dict) -> dict:
    from flax import serialization

    from harness.files import write_atomic
    from harness.octo.text import load_text_tokenizer
    from harness.policy import resize_frame

    path = folder / "example_batch.msgpack"
    batch = serialization.msgpack_restore(path.read_bytes())
    n = len(episode["action"])
    t = n // 2  # the middle frame
    obs = batch["observation"]
    for key in [k for k in obs if k.startswith("image_")]:
        size = tuple(np.shape(obs[key])[2:4])
        frame = episode[key][t]
        obs[key] = resize_frame(frame, size)[None, None].astype(np.uint8) if frame.shape[:2] != size \
            else frame[None, None].astype(np.uint8)
    obs["proprio"] = episode["proprio"][t][None, None].astype(np.float32)
    horizon = np.shape(batch["action"])[2]
    chunk = episode["action"][t:t + horizon]
    chunk = np.concatenate([chunk, np.repeat(chunk[-1:], horizon - len(chunk), 0)]) if len(chunk) < horizon else chunk
    batch["action"] = chunk[None, None].astype(np.float32)
    instruction = _instruction(family, source["task"])
    tokens = np.shape(batch["task"]["language_instruction"]["input_ids"])[1]
    encoded = load_text_tokenizer(str(folder / "tokenizer" / "tokenizer.json"), tokens).encode([instruction])
    batch["task"]["language_instruction"] = {k: np.asarray(v[:1]) for k, v in encoded.items()}
    data = serialization.msgpack_serialize(batch)
    write_atomic(path, lambda f: f.write(data))
    return {**source, "frame": t, "of": n, "instruction": instruction,
            "sizes": {k: list(np.shape(v)[2:4]) for k, v in obs.items() if k.startswith("image_")}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+", help="checkpoint folders of one family")
    parser.add_argument("--family", choices=("robosuite", "libero"), required=True)
    args = parser.parse_args()
    episode, source = _robosuite_demo() if args.family == "robosuite" else _libero_demo()  # one demonstration
    for folder in args.checkpoints:
        print(json.dumps({"checkpoint": folder.name, **rewrite(folder, args.family, episode, source)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Records the step-0 frames of LIBERO's published evaluation loop, written from LIBERO's public API alone.

The loop the published Octo/OpenVLA LIBERO numbers come from, as its steps read in LIBERO's API: make the task's
`OffScreenRenderEnv` from its BDDL file, seed it 0, reset it, restore one of the suite's stored initial states
with `set_init_state`, take 10 no-op actions (arm still, gripper open: [0, 0, 0, 0, 0, 0, -1]) so objects settle,
then turn each camera's frame by 180 degrees (`[::-1, ::-1]`), which is what the policy is fed. Nothing of the
harness is imported, so this is a recording of LIBERO's own path that the harness's default input is checked
against (tests/libero/test_published_protocol.py).

Run in LIBERO's environment (`bash scripts/setup_libero.sh` first):
    LIBERO_CONFIG_PATH=.venv-libero/libero-config .venv-libero/bin/python scripts/libero_published_frames.py \
        libero_object 0 0 OUT.npz [SIZE]
writes OUT.npz with `agentview` and `wrist` (SIZE x SIZE x 3 uint8, default 256 as the published evaluation).
"""

from __future__ import annotations

import os
import sys

import numpy as np

SETTLE_STEPS = 10
NO_OP = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]


def published_frames(suite_name: str, task_index: int, state_index: int, size: int = 256) -> dict[str, np.ndarray]:
    """{"agentview", "wrist"}: (size, size, 3) uint8 frames after the settle steps, turned by 180 degrees."""
    from libero.libero import benchmark, get_libero_path
    from libero.libero.envs import OffScreenRenderEnv

    suite = benchmark.get_benchmark_dict()[suite_name]()
    task = suite.get_task(task_index)
    states = suite.get_task_init_states(task_index)
    env = OffScreenRenderEnv(bddl_file_name=os.path.join(get_libero_path("bddl_files"), task.problem_folder,
                                                         task.bddl_file),
                             camera_heights=size, camera_widths=size)
    try:
        env.seed(0)
        env.reset()
        obs = env.set_init_state(states[state_index])
        for _ in range(SETTLE_STEPS):
            obs, _, _, _ = env.step(NO_OP)
        return {"agentview": np.ascontiguousarray(obs["agentview_image"][::-1, ::-1]),
                "wrist": np.ascontiguousarray(obs["robot0_eye_in_hand_image"][::-1, ::-1])}
    finally:
        env.close()


def main(argv: list[str]) -> int:
    if len(argv) not in (4, 5):
        print("usage: libero_published_frames.py SUITE TASK_INDEX STATE_INDEX OUT.npz [SIZE]", file=sys.stderr)
        return 2
    suite, task, state, out = argv[0], int(argv[1]), int(argv[2]), argv[3]
    frames = published_frames(suite, task, state, int(argv[4]) if len(argv) == 5 else 256)
    np.savez(out, **frames)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

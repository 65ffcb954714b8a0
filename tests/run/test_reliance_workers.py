"""Region reliance with any executor (issue 45): two env-worker processes give the sequential run's reliance.jsonl,
bit for bit (the masks travel with the request; the probe runs in the policy's process with the step's own rng)."""

from __future__ import annotations

import json

import pytest

import envs
from harness.outputs.writers import OutputOptions
from harness.policy import PolicyConfig
from harness.run import execute
from harness.run.protocol import Protocol
from harness.run.workers import WorkersExecutor

CAMERAS = (("image_primary", "agentview", 64), ("image_wrist", "robot0_eye_in_hand", 32))  # the tiny model's sizes


def _rows(summary) -> list[list[dict]]:
    """Each episode's reliance rows without the run's name."""
    out = []
    for row in summary.rows:
        lines = (summary.episode_dir(row) / "reliance.jsonl").read_text().splitlines()
        out.append([{k: v for k, v in json.loads(line).items() if k != "run"} for line in lines])
    return out


@pytest.mark.slow
def test_two_workers_give_the_sequential_reliance_bit_for_bit(fixtures_dir, tmp_path):
    from harness.octo import load_pretrained

    model = load_pretrained(str(fixtures_dir / "tiny"))
    protocol = Protocol(model=model.source, tasks=("Lift",), episodes=2, seed=5, max_steps=3,
                        env=envs.EnvOptions(masks=True, fast_render=True, cameras=CAMERAS),
                        policy=PolicyConfig(reliance_every=2), outputs=OutputOptions(png_every=0, video=False))
    sequential = execute(protocol, tmp_path, "seq", model=model, progress=False)
    parallel = execute(protocol, tmp_path, "two", model=model, progress=False,
                       executor=lambda context, m: WorkersExecutor(context, m, workers=2))
    assert [r.status for r in parallel.rows] == ["ok", "ok"]
    a, b = _rows(sequential), _rows(parallel)
    assert a == b  # every change, share and area: the same floats, not close ones
    assert {r["step"] for r in a[0]} == {0, 2} and {r["episode"] for e in a for r in e} == {0, 1}

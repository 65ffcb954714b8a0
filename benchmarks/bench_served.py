"""What serving a policy costs: the robosuite reference in-process against the same checkpoint behind
`octo-harness serve` (--model ws://), measured in one run on this machine.

Inference: seconds per request of the policy's stateless inference on real observation windows (Lift, one episode's
first steps): in-process (`load_policy(path).inference(config)`), served one request per frame, and served with the
batched extension (BATCH requests in one frame; the server still infers them one at a time at --inference-batch 1,
so only the round trips are shared). The ratio to in-process is the wire's cost (msgpack, the websocket, a second
process) per inference.

Closed loop: `octo-harness run` on the same episodes (outputs off: no PNG, no MP4), in-process sequential, served
sequential and served with --workers 2 (one connection, from the driver's inference server, which batches the
workers' requests into one frame up to --inference-batch): each episode's seconds per step, and the command's wall
time, start-up included (a served run's process loads no model). Actions must be bit-identical across all three
(checked, printed).

    .venv/bin/python benchmarks/bench_served.py [--episodes 2] [--steps 20] [--requests 20] [--json FILE]

Measured (2-core AMD EPYC VM, CPU only, loaded by a test run and a robustness grid at nice 19, so ratios only):
see docs/serving.md, "What serving costs".
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("HF_HUB_OFFLINE", "1")

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "models" / "octo-reference-robosuite"


def start_server(*flags: str) -> tuple[subprocess.Popen, str]:
    process = subprocess.Popen([sys.executable, "-m", "harness.cli", "serve", "--model", str(MODEL), "--port", "0",
                                *flags], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    for line in process.stdout:
        if line.startswith("serving "):
            return process, line.strip().rsplit(" on ", 1)[1]
    raise RuntimeError(f"the server exited ({process.wait()}) before its ready line")


def requests_of(policy, config, count: int) -> list:
    """Real observation windows: the first `count` steps of a Lift episode under the policy itself."""
    import envs
    from harness.policy import EpisodeState, PolicyStep, TaskPrompt

    env = envs.make("Lift", fast_render=True, action_space="robosuite", masks=False)
    inference = policy.inference(config)
    state = EpisodeState(policy.image_sizes, policy.window_size, policy.action_horizon, config,
                         TaskPrompt.of("lift the red cube"), 0, policy.lowdim_sizes)
    observation, _ = env.reset(seed=0)
    out = []
    while len(out) < count:
        decision = state.observe(observation)
        if not isinstance(decision, PolicyStep):
            out.append(decision)
            decision = state.complete(inference([decision])[0])
        observation, *_ = env.step(decision.action)
    env.close()
    return out


def per_request(inference, requests: list, batch: int = 1) -> float:
    inference.warm_up(requests[0])
    start = time.perf_counter()
    for i in range(0, len(requests), batch):
        inference(requests[i:i + batch])
    return (time.perf_counter() - start) / len(requests)


def run_rate(model: str, out: Path, name: str, episodes: int, steps: int, *extra: str) -> tuple[dict, Path]:
    """{"wall_s": the command's wall time (start-up included), "step_s": mean seconds per step of its episodes
    (results.jsonl's seconds_per_step: simulation, inference and harness, of every episode but the first, whose first
    inference compiles the model in-process)}."""
    argv = [sys.executable, "-m", "harness.cli", "run", "--model", model, "--task", "Lift", "--episodes", str(episodes),
            "--max-steps", str(steps), "--png-every", "0", "--no-video", "--fast-render", "--out", str(out),
            "--run-name", name, *extra]
    start = time.perf_counter()
    subprocess.run(argv, cwd=REPO, check=True, capture_output=True)
    wall = time.perf_counter() - start
    rows = [json.loads(line) for line in (out / name / "results.jsonl").read_text().splitlines() if line.strip()]
    timed = sorted(rows, key=lambda r: r["episode"])[1:] or rows  # the first episode compiles (in-process)
    return {"wall_s": wall, "step_s": sum(r["seconds_per_step"] for r in timed) / len(timed)}, out / name


def same_actions(a: Path, b: Path) -> bool:
    import numpy as np

    pairs = list(zip(sorted(a.rglob("actions.npz")), sorted(b.rglob("actions.npz"))))
    return bool(pairs) and all(np.array_equal(np.load(x)["executed"], np.load(y)["executed"]) for x, y in pairs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--requests", type=int, default=20)
    parser.add_argument("--batch", type=int, default=4, help="requests per extension frame [4]")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    from harness.conventions import CheckpointConventions
    from harness.policies import load_policy

    server, url = start_server("--max-batch", str(args.batch))
    try:
        local = load_policy(str(MODEL))
        config = CheckpointConventions.read(MODEL).policy_config()
        requests = requests_of(local, config, args.requests)
        served = load_policy(url)
        timings = {"in-process": per_request(local.inference(config), requests),
                   "served, 1 a frame": per_request(served.inference(config), requests),
                   f"served, {args.batch} a frame": per_request(served.inference(config), requests, args.batch)}
        served.close()
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp)
            rates = {}
            rates["in-process"], base = run_rate(str(MODEL), out, "local", args.episodes, args.steps)
            rates["served"], one = run_rate(url, out, "served", args.episodes, args.steps)
            rates["served, --workers 2"], two = run_rate(url, out, "workers", args.episodes, args.steps,
                                                         "--workers", "2")
            identical = same_actions(base, one) and same_actions(base, two)
    finally:
        server.terminate()
        server.wait(timeout=30)
    print(f"inference, seconds per request ({args.requests} real Lift windows):")
    for name, seconds in timings.items():
        print(f"  {name:<22} {seconds * 1000:8.2f} ms   {seconds / timings['in-process']:5.2f}x in-process")
    print(f"closed loop ({args.episodes} episodes x {args.steps} steps, outputs off): seconds per step of an episode, "
          "and the command's wall time (start-up included)")
    for name, rate in rates.items():
        print(f"  {name:<22} {rate['step_s']:7.3f} s/step {rate['step_s'] / rates['in-process']['step_s']:5.2f}x   "
              f"{rate['wall_s']:6.1f} s wall {rate['wall_s'] / rates['in-process']['wall_s']:5.2f}x")
    print(f"actions bit-identical in all three: {identical}")
    if args.json:
        args.json.write_text(json.dumps({"seconds_per_request": timings, "closed_loop": rates,
                                         "identical": identical}, indent=2))


if __name__ == "__main__":
    main()

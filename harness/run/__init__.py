"""Evaluation runs: protocol, run store, executors and the driver that ties them (see each module's docstring).

    from harness.run import execute, Protocol
    summary = execute(Protocol(model="random:octo-small-1.5", tasks=("Lift",), episodes=2), "results/runs")

jobs.py      EpisodeJob (task, episode, seed), FORMAT
protocol.py  Protocol (frozen, serialisable, fingerprinted), diff, model_fingerprint
settings.py  flags / protocol file (TOML) -> Protocol
checks.py    checks before anything heavy (one-line errors)
store.py     the run folder: lock, manifest, results.jsonl, derived tables, clean-up; EpisodeRow
executor.py  the executor interface, run_episode, SequentialExecutor
workers.py   WorkersExecutor: spawned env workers, inference batched in the driver
ray_executor.py  RayExecutor: env-worker actors and policy replicas on a Ray cluster
execution.py executor_factory: the execution flags -> which executor runs the episodes (the one place choosing)
driver.py    execute(): the pipeline, resume, signals, RunSummary
progress.py  progress bar
"""

import importlib

_EXPORTS = {
    "Interrupted": "driver", "ProtocolMismatchError": "driver", "RunSummary": "driver", "default_run_name": "driver",
    "execute": "driver", "EpisodeContext": "executor", "Executor": "executor", "SequentialExecutor": "executor",
    "make_env": "executor", "record_failure": "executor", "run_episode": "executor", "EpisodeJob": "jobs",
    "Protocol": "protocol", "diff": "protocol", "model_fingerprint": "protocol", "EpisodeRow": "store",
    "ResultsWriteError": "store", "RunLockedError": "store", "RunStore": "store", "executor_factory": "execution",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    """Lazy exports: readers importing harness.run.store do not pay for the simulator and model imports."""
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"harness.run.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'harness.run' has no attribute {name!r}")

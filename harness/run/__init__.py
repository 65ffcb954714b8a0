"""Evaluation runs: protocol, run store, executors and the driver that ties them (see each module's docstring).

    from harness.run import execute, Protocol
    summary = execute(Protocol(model="random:octo-small-1.5", tasks=("Lift",), episodes=2), "results/runs")

protocol.py  Protocol (frozen, serialisable, fingerprinted), EpisodeJob, diff, model_fingerprint
settings.py  flags / protocol file (TOML) -> Protocol
checks.py    checks before anything heavy (one-line errors)
store.py     the run folder: lock, manifest, results.jsonl, derived tables, clean-up; EpisodeRow
executor.py  the executor interface, run_episode, SequentialExecutor
driver.py    execute(): the pipeline, resume, signals, RunSummary
progress.py  progress bar
"""

from harness.run.driver import Interrupted, ProtocolMismatchError, RunSummary, default_run_name, execute
from harness.run.executor import EpisodeContext, Executor, SequentialExecutor, make_env, record_failure, run_episode
from harness.run.protocol import EpisodeJob, Protocol, diff, model_fingerprint
from harness.run.store import EpisodeRow, ResultsWriteError, RunLockedError, RunStore

__all__ = [
    "EpisodeContext", "EpisodeJob", "EpisodeRow", "Executor", "Interrupted", "Protocol", "ProtocolMismatchError",
    "ResultsWriteError", "RunLockedError", "RunStore", "RunSummary", "SequentialExecutor", "default_run_name", "diff",
    "execute", "make_env", "model_fingerprint", "record_failure", "run_episode",
]

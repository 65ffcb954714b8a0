"""Where a run's episodes execute: the one place that maps the execution flags (--workers, --executor, --ray-address,
--policy-replicas) to an executor factory for `harness.run.execute` (None: the sequential executor).

The executors themselves (`executor.SequentialExecutor`, `workers.WorkersExecutor`, `ray_executor.RayExecutor`)
do not choose each other: the Ray executor builds on the local workers' pieces, the local workers know nothing of
Ray, and only this module imports both (Ray lazily, as it is optional).
"""

from __future__ import annotations

import functools
import os

from harness.run.workers import WorkersExecutor, max_workers

DEFAULT_EXECUTOR = "local"  # where env workers run when --executor is not given
DEFAULT_REPLICAS = 1  # Ray: model replicas when --policy-replicas is not given (None: not given, so it needs ray)


def executor_factory(workers: int | None, executor: str | None = None, ray_address: str | None = None,
                     policy_replicas: int | None = None):
    """Command-line execution options -> an executor factory for `execute` (None = the sequential executor).

    Checked before anything heavy: one line naming the fix for an impossible combination, or Ray missing.
    """
    executor = executor or DEFAULT_EXECUTOR
    if workers is not None and workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")
    on_this_machine = not (executor == "ray" and ray_address is not None)  # a cluster's CPUs are checked when it is joined
    if workers is not None and on_this_machine and workers > max_workers():
        raise ValueError(f"--workers {workers} is more than this machine can use ({os.cpu_count()} CPU cores, "
                         f"memory for {max_workers()} env workers); use --workers {max_workers()} or fewer")
    if executor != "ray" and (ray_address is not None or policy_replicas is not None):
        raise ValueError("--ray-address and --policy-replicas need --executor ray")
    if policy_replicas is not None and policy_replicas < 1:
        raise ValueError(f"--policy-replicas must be at least 1, got {policy_replicas}")
    if executor == "ray":
        from harness.run.ray_executor import RayExecutor, import_ray

        import_ray()
        return functools.partial(RayExecutor, workers=workers, address=ray_address,
                                 replicas=policy_replicas or DEFAULT_REPLICAS)
    if workers is None:
        return None
    return functools.partial(WorkersExecutor, workers=workers)

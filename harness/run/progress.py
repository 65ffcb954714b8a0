"""Progress of a run on stderr: a tqdm bar over the run's episodes (successes so far, ETA) on a terminal,
one plain line per finished episode otherwise (logs of batch jobs stay readable)."""

from __future__ import annotations

import sys
import time
from typing import TextIO

from harness.run.jobs import EpisodeJob
from harness.run.store import EpisodeRow


class Progress:
    def __init__(self, total: int, done: int = 0, successes: int = 0, stream: TextIO | None = None):
        self.total, self.done, self.successes, self.failed = total, done, successes, 0
        self.stream = stream or sys.stderr
        self.start = time.perf_counter()
        self.finished_here = 0
        self.bar = None
        self._shown = 0.0
        if self.stream.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=done, unit="episode", file=self.stream, dynamic_ncols=True,
                            desc="episodes")
            self.bar.set_postfix_str(self._postfix())

    def _postfix(self, extra: str = "") -> str:
        text = f"success {self.successes}/{self.done}" + (f", failed {self.failed}" if self.failed else "")
        return text + (f" | {extra}" if extra else "")

    def step(self, job: EpisodeJob, t: int, record) -> None:
        if self.bar is not None:
            now = time.perf_counter()
            refresh = now - self._shown >= 0.5  # redraw at most twice a second
            self._shown = now if refresh else self._shown
            self.bar.set_postfix_str(self._postfix(f"{job.directory} step {t + 1}"), refresh=refresh)

    def episode(self, row: EpisodeRow) -> None:
        self.done += 1
        self.finished_here += 1
        self.successes += int(row.status == "ok" and bool(row.success))
        self.failed += int(row.status != "ok")
        if self.bar is not None:
            self.bar.set_postfix_str(self._postfix(), refresh=False)
            self.bar.update(1)
            return
        elapsed = time.perf_counter() - self.start
        left = self.total - self.done
        eta = elapsed / self.finished_here * left
        outcome = "FAILED" if row.status != "ok" else ("success" if row.success else "no success")
        print(f"[{self.done}/{self.total}] {row.directory}: {outcome} ({row.steps} steps) | "
              f"success {self.successes}/{self.done} | ETA {_duration(eta)}", file=self.stream, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m" if h else (f"{m}m{s:02d}s" if m else f"{s}s")

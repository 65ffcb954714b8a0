"""Episode jobs and the run-folder format name: the light part of a protocol that readers of run folders need.

A job is one episode to run, `(task, episode index, seed)`; its outputs live in `<run>/<task>/episode_<k>/`.
"""

from __future__ import annotations

from dataclasses import dataclass

FORMAT = "octo-harness-run/1"


@dataclass(frozen=True, order=True)
class EpisodeJob:
    """One episode to run: the unit executors receive. `directory` is relative to the run folder."""

    task: str
    episode: int
    seed: int

    @property
    def key(self) -> tuple[str, int]:
        return (self.task, self.episode)

    @property
    def directory(self) -> str:
        return f"{self.task}/episode_{self.episode}"

"""The table of an episode's outputs: one sink class per output, in the order the episode writer drives them.

A new output is one `Sink` subclass (harness.outputs.steps) and one entry here; a per-step probe's files are the sink
its probe declares (harness.probes), found through the registry. Every step goes to the sinks in this
order, and the files are written in it when the episode closes (the data files first, the recording last).
"""

from __future__ import annotations

from pathlib import Path

from harness import probes
from harness.outputs.data_files import ActionArrays, AttentionArrays, InputArrays, MetricLines
from harness.outputs.panels import PngPanels
from harness.outputs.rerun_sink import RerunRecording
from harness.outputs.rollout_video import RolloutVideo
from harness.outputs.steps import Sink
from harness.records import EpisodeMeta

DATA_SINKS: tuple[type[Sink], ...] = (
    AttentionArrays,  # attention.npz
    ActionArrays,  # actions.npz
    InputArrays,  # inputs.npz (record_inputs)
    MetricLines,  # metrics.jsonl
)
VIEW_SINKS: tuple[type[Sink], ...] = (
    PngPanels,  # step_<tttt>_layer_<ll>.png, step_<tttt>_attribution.png
    RolloutVideo,  # rollout.mp4, rollout.gif
    RerunRecording,  # episode.rrd and/or a live viewer (--rerun)
)


def sink_table() -> tuple[type[Sink], ...]:
    """The sinks in the order the writer drives them: the data sinks, then each registered probe's sink
    (harness.probes, in registry order: attribution.npz and faithfulness.jsonl, controls.npz, the region probe's
    rows, then any probe registered later), then the pictures and the recording."""
    return (*DATA_SINKS, *(sink for _, sink in probes.parts("sink")), *VIEW_SINKS)


def open_sinks(directory: Path, meta: EpisodeMeta, options, viewer: str | None = None) -> list[Sink]:
    """The sinks of `sink_table()` that `options` (OutputOptions) and `viewer` (a live viewer's gRPC url) ask for, made in
    order; when one cannot be made (the Rerun extra is missing), those made before it are aborted."""
    sinks: list[Sink] = []
    try:
        for cls in sink_table():
            if cls.wanted(options, viewer):
                sinks.append(cls(directory, meta, options, viewer))
    except BaseException:
        for sink in sinks:
            sink.abort()
        raise
    return sinks

"""The table of an episode's outputs: one sink class per output, in the order the episode writer drives them.

A new output is one `Sink` subclass (harness.outputs.steps) and one entry here. Every step goes to the sinks in this
order, and the files are written in it when the episode closes (the data files first, the recording last).
"""

from __future__ import annotations

from pathlib import Path

from harness.outputs.data_files import (ActionArrays, AttentionArrays, AttributionFiles, ControlArrays, InputArrays,
                                        MetricLines, RelianceLines)
from harness.outputs.panels import PngPanels
from harness.outputs.rerun_sink import RerunRecording
from harness.outputs.rollout_video import RolloutVideo
from harness.outputs.steps import Sink
from harness.records import EpisodeMeta

SINKS: tuple[type[Sink], ...] = (
    AttentionArrays,  # attention.npz
    ActionArrays,  # actions.npz
    InputArrays,  # inputs.npz (record_inputs)
    MetricLines,  # metrics.jsonl
    AttributionFiles,  # attribution.npz, faithfulness.jsonl (steps with attribution maps)
    ControlArrays,  # controls.npz (--attention-controls)
    RelianceLines,  # reliance.jsonl (--reliance-every)
    PngPanels,  # step_<tttt>_layer_<ll>.png, step_<tttt>_attribution.png
    RolloutVideo,  # rollout.mp4, rollout.gif
    RerunRecording,  # episode.rrd and/or a live viewer (--rerun)
)


def open_sinks(directory: Path, meta: EpisodeMeta, options, viewer: str | None = None) -> list[Sink]:
    """The sinks of SINKS that `options` (OutputOptions) and `viewer` (a live viewer's gRPC url) ask for, made in
    order; when one cannot be made (the Rerun extra is missing), those made before it are aborted."""
    sinks: list[Sink] = []
    try:
        for cls in SINKS:
            if cls.wanted(options, viewer):
                sinks.append(cls(directory, meta, options, viewer))
    except BaseException:
        for sink in sinks:
            sink.abort()
        raise
    return sinks

"""The viewer shows reliance: a Rerun recording made by the episode writer's Rerun sink alone from hand-made step
records with reliance rows holds each region's reliance share on the step timeline at the reliance steps only, read
back with Rerun's own loader; a null share (camera not used) is not logged."""

from __future__ import annotations

import numpy as np
import rerun as rr

from harness.outputs.writers import OutputOptions
from harness.outputs.rerun_sink import RRD_NAME, RerunRecording
from tests.outputs.test_sinks import STEPS, drive, with_extras
from tests.outputs.test_writers import records


def _rows(step: int, target: float, used: bool = True) -> list[dict]:
    return [{"step": step, "camera": camera, "region": region, "fill": "impute", "change": 0.1,
             "area_fraction": 0.25, "reliance_per_pixel": 0.4,
             "reliance_share": (share if used or camera == "image_wrist" else None), "camera_change": 0.4}
            for camera in ("image_primary", "image_wrist")
            for region, share in (("target", target), ("background", 1 - target))]


def _column(path, entity: str) -> tuple[list, list]:
    rec = rr.dataframe.load_recording(str(path))
    table = rec.view(index="step", contents=entity).select(columns=["step", f"{entity}:Scalar"]).read_all()
    values = [v for v in table.column(f"{entity}:Scalar").to_pylist()]
    steps = [s for s, v in zip(table.column("step").to_pylist(), values) if v is not None]
    return steps, [v[0] for v in values if v is not None]


def test_reliance_shares_are_scalars_on_the_timeline_at_reliance_steps(tmp_path):
    assert STEPS >= 3
    recs = with_extras(records(STEPS), reliance={0: {"rows": _rows(0, 0.75), "seconds": 0.1},
                                                 2: {"rows": _rows(2, 0.5, used=False), "seconds": 0.1}})
    drive(RerunRecording, tmp_path, recs, options=OutputOptions(rerun=True, png_every=0, video=False))
    rrd = tmp_path / RRD_NAME
    steps, values = _column(rrd, "/reliance/image_primary/target")
    assert steps == [0] and np.allclose(values, [0.75])  # step 2: the primary camera unused, nothing logged
    steps, values = _column(rrd, "/reliance/image_wrist/background")
    assert steps == [0, 2] and np.allclose(values, [0.25, 0.5])

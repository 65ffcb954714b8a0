"""`octo-harness robustness`: `camera` and `noise` without @KEY give one cell per camera the model reads (issue 43
item 2), named after the camera in folders, the grid file and the tables; a grid made before keeps its run names."""

from __future__ import annotations

import json

import pytest

from harness.gate.robustness import expand_conditions, grid, model_camera_keys

KEYS = ("image_primary", "image_wrist")


def test_bare_keyed_kinds_expand_per_camera_and_explicit_ones_stay():
    assert expand_conditions(("camera", "lighting", "noise"), KEYS) == (
        "camera@image_primary", "camera@image_wrist", "lighting", "noise@image_primary", "noise@image_wrist")
    assert expand_conditions(("camera@image_wrist", "camera"), KEYS) == ("camera@image_wrist", "camera@image_primary")
    assert expand_conditions(("camera",), ("image_primary",)) == ("camera@image_primary",)
    assert expand_conditions(("texture",), KEYS) == ("texture",)
    names = grid(expand_conditions(("camera",), KEYS), (0, 3))
    assert names == {"nominal": None, "camera@image_primary-3": "camera@image_primary:3",
                     "camera@image_wrist-3": "camera@image_wrist:3"}


@pytest.mark.slow
def test_a_tiny_camera_grid_has_a_cell_per_camera_and_keeps_an_old_grids_names(fixtures_dir, tmp_path):
    from harness.analysis.robustness import collect, paired_rows
    from harness.analysis.runs import load_run
    from harness.octo import load_pretrained
    from harness.gate.robustness import run_grid
    from harness.run.settings import build_protocol

    model = load_pretrained(str(fixtures_dir / "tiny"))
    assert model_camera_keys(model) == KEYS
    out = tmp_path / "grid"
    out.mkdir()
    # a grid file written before the expansion: camera@image_primary:1 ran as "camera-1"
    (out / "robustness.json").write_text(json.dumps({"format": "octo-harness-robustness/1", "conditions": ["camera"],
                                                     "levels": [1], "tasks": ["Lift"],
                                                     "runs": {"camera-1": "camera@image_primary:1"}}))
    base = build_protocol({"task": ["Lift"], "model": str(fixtures_dir / "tiny"), "max_steps": 2, "png_every": 0,
                           "no_video": True, "fast_render": True})
    summaries = run_grid(base, ("camera",), (1,), out, model=model, progress=False)
    assert set(summaries) == {"camera-1", "camera@image_wrist-1"}
    record = json.loads((out / "robustness.json").read_text())
    assert record["conditions"] == ["camera", "camera@image_primary", "camera@image_wrist"]
    assert record["runs"] == {"camera-1": "camera@image_primary:1", "camera@image_wrist-1": "camera@image_wrist:1"}
    rows, _, _ = collect([load_run(out / name) for name in summaries])
    assert sorted({r.condition for r in rows}) == ["camera@image_primary", "camera@image_wrist"]
    paired = paired_rows(rows)  # no nominal run in this grid: a cell per camera, no pairs
    assert [(p.condition, p.pairs) for p in paired] == [("camera@image_primary", 0), ("camera@image_wrist", 0)]

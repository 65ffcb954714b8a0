"""How an episode looks in Rerun: its entity tree, the images drawn for it and the default blueprint.

Timelines: `step` (the control step) and `sim_time` (step / control frequency, seconds). Entity tree (logged by
harness.outputs.rerun_sink.RerunSink):

  camera/<obs key>                     the frame the model saw (JPEG), upright
  camera/<obs key>/target              the target object's mask (class 1) over it, logged when it changes
  camera/<obs key>/<probe>             a probe's layer over it (harness.probes; logged at the probe's steps only,
                                       so a step shows the layer of the last one at or before it)
  attention/<obs key>/layer_<ll>       that layer's head-mean readout attention drawn over the frame (JPEG; the frame
                                       shrunk by an integer factor to at most 128 px high, `overlay_base`)
  attention/<obs key>/heads            (layer, head, row, col) float32 tensor: every head's map, readouts averaged,
                                       from the attention rounded to float16 as attention.npz stores it (equal values)
  <probe>/...                          what each per-step probe's viewer layer logs at the steps that carry it
                                       (harness.probes: attribution/<method>/<obs key> maps over the frame; a
                                       share per camera and region on the timeline)
  intervention/<obs key>               what the policy was fed when an intervention masks its inputs (--intervene)
  actions/executed, actions/predicted  the action sent to the env; the first action of this step's chunk
  actions/chunk                        (horizon, action dim) tensor: the predicted chunk
  scalars/reward, scalars/success      per step
  scalars/new_chunk                    a marker (1) at every step where a new action chunk was inferred
  measures/share/<group>, measures/timestep_share/<part>, measures/entropy, measures/mask_mass/<obs>/<mask>,
  measures/mask_lift/<obs>/<mask>      per layer, one series each (attention.step_metrics; lift = mass / area)
  episode/instruction, episode/outcome text documents (static)
"""

from __future__ import annotations

import io
import re

import numpy as np
from PIL import Image

TARGET_COLOUR = (0, 255, 0, 110)  # RGBA of target pixels; the rest is transparent
LAYER_DRAW_ORDER = 0.0  # a probe's transparent layer over a frame: above it (images default to -10), below the target (5)
OVERLAY_HEIGHT = 128  # overlays are drawn on the frame shrunk by an integer factor to at most this height (size, time)


def entity(*parts: str) -> str:
    """An entity path from parts that may hold characters Rerun reserves (e.g. '/' inside a mask name)."""
    return "/".join(re.sub(r"[^A-Za-z0-9_\-.]", "_", str(p)) for p in parts)


def overlay_base(frame: np.ndarray, height: int = OVERLAY_HEIGHT) -> np.ndarray:
    """frame (H, W, 3) -> the frame the overlays are drawn on: every k-th pixel, k the smallest integer factor that
    brings the height to at most `height` (k = 1 for small frames); maps are at most a 16 x 16 patch grid."""
    k = max(1, -(-frame.shape[0] // height))
    return np.ascontiguousarray(frame[::k, ::k])


def mask_png(mask: np.ndarray) -> bytes:
    """mask (H, W) bool -> PNG bytes, RGBA: TARGET_COLOUR where True, transparent elsewhere (a few hundred bytes)."""
    rgba = np.zeros((*mask.shape, 4), np.uint8)
    rgba[mask] = TARGET_COLOUR
    out = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(out, format="PNG", optimize=False, compress_level=6)
    return out.getvalue()


def blueprint(cameras: list[str], layers: int, intervention: bool = False, shown: list = (), attention: bool = True):
    """The default layout: per camera its frame (with masks, and the probes' layers over it) beside the layer tabs
    of attention overlays (last layer shown); the per-head tensor with sliders over layer and head; the probes' views
    of the camera (attribution maps) in tabs; the measures (and the probes' plots, e.g. a share per region and
    camera), actions and rewards on the timeline; the instruction and outcome. `shown`: (viewer layer, payload)
    of the probes at the first step (harness.probes: `camera_views(cam, payload)`, `camera_note(payload)`,
    `plots(payload)`). attention=False (a policy that gives none): per camera its frame only, and no measures."""
    import rerun.blueprint as rrb
    from rerun.blueprint.datatypes import TensorDimensionIndexSlider
    from rerun.datatypes import TensorDimensionIndexSelection, TensorDimensionSelection

    if not attention:
        return _plain_blueprint(rrb, cameras, intervention)
    image_rows = []
    for cam in cameras:
        names = [f"{cam} layer {layer}" for layer in range(layers)]
        layer_tabs = rrb.Tabs(*[rrb.Spatial2DView(origin=entity("attention", cam, f"layer_{layer:02d}"), name=name)
                                for layer, name in enumerate(names)],
                              active_tab=names[-1] if names else None, name=f"{cam} attention by layer")
        extra = [view for layer, payload in shown for view in layer.camera_views(cam, payload)]
        if intervention:
            extra.append(rrb.Spatial2DView(origin=entity("intervention", cam), name=f"{cam} as the policy saw it"))
        heads = rrb.TensorView(
            origin=entity("attention", cam, "heads"), name=f"{cam} every head (sliders: layer, head)",
            slice_selection=rrb.TensorSliceSelection(
                width=TensorDimensionSelection(3), height=TensorDimensionSelection(2),
                indices=[TensorDimensionIndexSelection(0, max(layers - 1, 0)), TensorDimensionIndexSelection(1, 0)],
                slider=[TensorDimensionIndexSlider(0), TensorDimensionIndexSlider(1)]),
            scalar_mapping=rrb.TensorScalarMapping(colormap="viridis", mag_filter="nearest"),
        )
        notes = [note for layer, payload in shown for note in [layer.camera_note(payload)] if note]
        views = [rrb.Spatial2DView(origin=entity("camera", cam), name=", ".join([cam, *notes])),
                 layer_tabs, heads]
        if extra:
            views.append(rrb.Tabs(*extra, name=f"{cam} attribution"))
        image_rows.append(rrb.Horizontal(*views))
    measures = rrb.Tabs(
        rrb.TimeSeriesView(origin="measures/mask_lift", contents=[entity("measures", "mask_lift", cam, "target")
                                                                  for cam in cameras],
                           name="target lift per layer (1 = chance)"),
        rrb.TimeSeriesView(origin="measures/share", name="modality shares per layer"),
        rrb.TimeSeriesView(origin="measures/timestep_share", name="timestep shares per layer"),
        rrb.TimeSeriesView(origin="measures/entropy", name="entropy per layer"),
        rrb.TimeSeriesView(origin="measures/mask_mass", name="mask mass per layer"),
        *[view for layer, payload in shown for view in layer.plots(payload)],
        active_tab="target lift per layer (1 = chance)", name="attention measures")
    plots = rrb.Vertical(
        measures,
        rrb.TimeSeriesView(origin="actions", name="actions (executed; first of the predicted chunk)"),
        rrb.TimeSeriesView(origin="scalars", name="reward, success, new chunks"),
        rrb.Horizontal(rrb.TextDocumentView(origin="episode/instruction", name="episode"),
                       rrb.TextDocumentView(origin="episode/outcome", name="outcome")),
        row_shares=[3, 2, 1.5, 1.5],
    )
    return rrb.Blueprint(rrb.Horizontal(rrb.Vertical(*image_rows), plots, column_shares=[3, 2]),
                         rrb.TimePanel(expanded=True), collapse_panels=True)


def _plain_blueprint(rrb, cameras: list[str], intervention: bool):
    """The layout of an episode without attention: each camera's frame (with its masks), actions, scalars, text."""
    rows = [rrb.Horizontal(rrb.Spatial2DView(origin=entity("camera", cam), name=cam),
                           *([rrb.Spatial2DView(origin=entity("intervention", cam), name=f"{cam} as the policy saw it")]
                             if intervention else [])) for cam in cameras]
    plots = rrb.Vertical(
        rrb.TimeSeriesView(origin="actions", name="actions (executed; first of the predicted chunk)"),
        rrb.TimeSeriesView(origin="scalars", name="reward, success, new chunks"),
        rrb.Horizontal(rrb.TextDocumentView(origin="episode/instruction", name="episode"),
                       rrb.TextDocumentView(origin="episode/outcome", name="outcome")),
        row_shares=[2, 1.5, 1.5],
    )
    return rrb.Blueprint(rrb.Horizontal(rrb.Vertical(*rows), plots, column_shares=[3, 2]),
                         rrb.TimePanel(expanded=True), collapse_panels=True)

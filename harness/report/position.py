"""The report's Position section: how much of each patch's attention is bound to position rather than content.

From runs made with `--attention-controls blank,mirror` (controls.npz per episode) and the real attention of the
same steps (attention.npz), per run x task x camera (harness.analysis.position for the definitions and flag rule):

  position_bound.csv   run, task, camera, layer, head (a number or "mean"), row, col, real, blank, mirrored,
                       flagged: mean attention of each patch over the control steps on the real, blank and mirrored
                       frames (mirrored: the same position), and the flag
  position_share.csv   run, task, camera, layer, head, steps, remaining_share (sum min(blank, real) / sum real),
                       follows_share (sum min(mirrored at the mirror-image patch, real) / sum real), flagged_patches,
                       flagged_share (real attention on flagged patches / all)
  position_lift.csv    run, task, camera, layer, mask, steps, lift_real, lift_content: lift of the target, gripper and
                       goal masks at the control steps with the real map and with the content-only view (head mean)

`tables(runs)`, `section(runs, plots)` ("" when no run has controls), `markdown(runs)` (python -m
harness.report.position RUN...).
"""

from __future__ import annotations

import io
import warnings
from collections import defaultdict

import numpy as np

from harness.analysis import position as Q
from harness.measures.attention import camera_maps
from harness.analysis.runs import read_npz
from harness.octo.tokens import TokenMap
from harness.report import html as H
from harness.report.rundata import csv_bytes as _csv

BOUND_COLUMNS = ("run", "task", "camera", "layer", "head", "row", "col", "real", "blank", "mirrored", "flagged")
SHARE_COLUMNS = ("run", "task", "camera", "layer", "head", "steps", "remaining_share", "follows_share",
                 "flagged_patches", "flagged_share")
LIFT_COLUMNS = ("run", "task", "camera", "layer", "mask", "steps", "lift_real", "lift_content")
LIFT_MASKS = ("target", "gripper", "goal")


def _label(run) -> str:
    return getattr(run, "label", getattr(run, "name", ""))


def _episode_maps(e) -> dict | None:
    """{camera: (real, blank, mirror) (steps, layers, heads, rows, cols), "fractions": {cam/mask: (steps, r, c)},
    "frame": {camera: (H, W, 3) uint8 or None}} at one episode's control steps; None without usable controls."""
    controls_path = e.directory / "controls.npz"
    if not e.ok or not controls_path.is_file() or not e.attention_path.is_file():
        return None
    try:
        controls = read_npz(controls_path)
        arrays = read_npz(e.attention_path)
    except ValueError:
        return None
    if "step" not in controls or "readout_attention" not in arrays or not {"blank", "mirror"} <= set(controls):
        return None
    tokens = TokenMap.from_arrays({k: v for k, v in arrays.items() if k.startswith("tokens/")})
    steps = np.asarray(arrays.get("step", np.arange(len(arrays["readout_attention"]))))
    index = {int(s): i for i, s in enumerate(steps)}
    wanted = [int(s) for s in controls["step"]]
    if any(s not in index for s in wanted):
        return None  # controls of steps the episode did not record: not this episode's file
    rows = [index[s] for s in wanted]
    real = np.asarray(arrays["readout_attention"][rows], np.float32)
    blank = np.asarray(controls["blank"], np.float32)
    mirror = np.asarray(controls["mirror"], np.float32)
    if not real.shape == blank.shape == mirror.shape:
        return None
    out = {"cameras": {}, "fractions": {}, "frame": {}}
    for _, cam, _, _ in tokens.image_groups:
        maps = [camera_maps(x, tokens, cam).mean(axis=3) for x in (real, blank, mirror)]  # (steps, layers, heads, r, c)
        if not np.all([np.isfinite(m).all() for m in maps]):
            return None
        out["cameras"][cam] = maps
        for mask in LIFT_MASKS:
            key = f"mask_fraction/{cam}/{mask}"
            if key in arrays and len(arrays[key]) == len(steps):
                out["fractions"][f"{cam}/{mask}"] = np.asarray(arrays[key][rows], np.float64)
    inputs = e.directory / "inputs.npz"
    if inputs.is_file():
        try:
            recorded = read_npz(inputs)
            out["frame"] = {cam: recorded[f"input/{cam}"][rows[0]] for cam in out["cameras"] if f"input/{cam}" in recorded}
        except (ValueError, IndexError):
            pass
    return out


def summarise(run) -> dict:
    """{"bound", "share", "lift": rows, "maps": {(task, camera): (PatchMeans, flags, frame, content mean)}}."""
    label = _label(run)
    record = getattr(run, "record", run)
    pooled: dict[tuple[str, str], list] = defaultdict(lambda: [[], [], [], []])
    frames: dict[tuple[str, str], np.ndarray] = {}
    for e in record.episodes:
        data = _episode_maps(e)
        if data is None:
            continue
        for cam, (real, blank, mirror) in data["cameras"].items():
            lists = pooled[(e.task, cam)]
            if lists[0] and lists[0][0].shape[1:] != real.shape[1:]:
                continue  # another model's layout in the same run: left out
            lists[0].append(real), lists[1].append(blank), lists[2].append(mirror)
            lists[3].append({m: data["fractions"].get(f"{cam}/{m}") for m in LIFT_MASKS})
            if cam in data["frame"] and (e.task, cam) not in frames:
                frames[(e.task, cam)] = data["frame"][cam]
    out = {"bound": [], "share": [], "lift": [], "maps": {}}
    for (task, cam), (reals, blanks, mirrors, fracs) in pooled.items():
        real, blank, mirror = (np.concatenate(x) for x in (reals, blanks, mirrors))
        means = Q.patch_means(real, blank, mirror)
        flags = Q.flag_position_bound(means.real, means.blank, means.mirrored)
        remain = Q.remaining_share(means.real, means.blank)
        follows = Q.remaining_share(means.real, means.followed)
        fshare = Q.flagged_share(means.real, flags)
        layers, heads1, rows, cols = means.real.shape
        for layer in range(layers):
            for h in range(heads1):
                head = "mean" if h == heads1 - 1 else h
                out["share"].append((label, task, cam, layer, head, means.steps, float(remain[layer, h]),
                                     float(follows[layer, h]), int(flags[layer, h].sum()), float(fshare[layer, h])))
                for r in range(rows):
                    for c in range(cols):
                        out["bound"].append((label, task, cam, layer, head, r, c, float(means.real[layer, h, r, c]),
                                             float(means.blank[layer, h, r, c]), float(means.mirrored[layer, h, r, c]),
                                             bool(flags[layer, h, r, c])))
        real_mean, blank_mean = real.mean(axis=2), blank.mean(axis=2)  # head mean (steps, layers, r, c)
        content = Q.content_only(real_mean, blank_mean)
        for mask in LIFT_MASKS:
            parts = [(i, f[mask]) for i, f in enumerate(fracs) if f.get(mask) is not None]
            if not parts:
                continue
            fraction = np.concatenate([np.broadcast_to(f[:, None], (len(f), layers, rows, cols)) for _, f in parts])
            offsets = np.cumsum([0] + [len(x) for x in reals])  # each episode's control steps in the pooled arrays
            idx = np.concatenate([np.arange(offsets[i], offsets[i + 1]) for i, _ in parts])
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # a layer without any value: nan, said as "n/a"
                lr = np.nanmean(Q.mask_lift(real_mean[idx], fraction), axis=0)
                lc = np.nanmean(Q.mask_lift(content[idx], fraction), axis=0)
            for layer in range(layers):
                out["lift"].append((label, task, cam, layer, mask, len(idx), float(lr[layer]), float(lc[layer])))
        out["maps"][(task, cam)] = (means, flags, frames.get((task, cam)), content.mean(axis=0))
    return out




def tables(runs, summaries: list | None = None) -> dict[str, bytes]:
    """{"position_bound.csv", "position_share.csv", "position_lift.csv"} (header only without controls)."""
    summaries = summaries if summaries is not None else [summarise(run) for run in runs]
    join = lambda name: [r for s in summaries for r in s[name]]  # noqa: E731
    return {"position_bound.csv": _csv(BOUND_COLUMNS, join("bound")), "position_share.csv": _csv(SHARE_COLUMNS, join("share")),
            "position_lift.csv": _csv(LIFT_COLUMNS, join("lift"))}


def figure(task: str, maps: dict) -> bytes:
    """PNG: rows = cameras x (real attention with flagged patches boxed, content-only view), columns = layers (head
    mean, mean over control steps), drawn over the episode's first control frame when recorded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    cams = [c for (t, c) in maps if t == task]
    layers = maps[(task, cams[0])][0].real.shape[0]
    fig, axes = plt.subplots(2 * len(cams), layers, figsize=(2.1 * layers, 2.2 * 2 * len(cams)), dpi=100, squeeze=False)
    for ci, cam in enumerate(cams):
        means, flags, frame, content = maps[(task, cam)]
        rows, cols = means.real.shape[-2:]
        for layer in range(layers):
            for k, (grid, title) in enumerate(((means.real[layer, -1], "attention"), (content[layer], "content only"))):
                ax = axes[2 * ci + k][layer]
                if frame is not None:
                    ax.imshow(frame, extent=(0, cols, rows, 0))
                ax.imshow(grid, cmap="inferno", alpha=0.6 if frame is not None else 1.0, extent=(0, cols, rows, 0))
                if k == 0:
                    for r, c in zip(*np.nonzero(flags[layer, -1])):
                        ax.add_patch(Rectangle((c, r), 1, 1, fill=False, edgecolor="#00e5ff", lw=2))
                ax.set_xticks([]), ax.set_yticks([])
                ax.set_title(f"{cam.removeprefix('image_')} L{layer} {title}", fontsize=7)
    fig.suptitle(f"{task}: mean readout attention (head mean); cyan boxes: position-bound patches", fontsize=8)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def _flagged_list(summary, task: str, cam: str, layer: int) -> str:
    cells = [f"({r[5]},{r[6]})" for r in summary["bound"] if r[1] == task and r[2] == cam and r[3] == layer
             and r[4] == "mean" and r[10]]
    return " ".join(cells) if cells else "none"


def sentence(task: str, summary: dict) -> str:
    """A verdict line per task (at most about 25 words with two cameras): per camera, the range over layers of the
    head mean's attention that remains on a blank frame, and in how many layers patches are flagged. The shares per
    layer, the mirror's and the flagged patches are the table's."""
    parts = []
    for cam in dict.fromkeys(r[2] for r in summary["share"] if r[1] == task):
        rows = [r for r in summary["share"] if r[1] == task and r[2] == cam and r[4] == "mean"]
        flagged = sum(1 for r in rows if r[8])
        parts.append(f"{cam} {min(r[6] for r in rows):.0%}-{max(r[6] for r in rows):.0%} remains on a blank frame, "
                     f"flagged in {flagged}/{len(rows)} layers")
    return f"{task}: " + "; ".join(parts) + "." if parts else f"{task}: no controls recorded."


def section(runs, plots, summaries: list | None = None) -> str:
    """The page's Position section ("" when no run has attention controls)."""
    summaries = summaries if summaries is not None else [summarise(run) for run in runs]
    body = []
    for run, summary in zip(runs, summaries):
        for task in dict.fromkeys(r[1] for r in summary["share"]):
            body.append(H.section(f"{task}: {_label(run)}", "", level=3))
            body.append(H.Raw(f"<p>{H.esc(sentence(task, summary))}</p>"))
            body.append(H.table(("camera", "layer", "control steps", "remains blank", "follows the mirror",
                                 "flagged patches (row,col)", "attention on flagged"),
                                [(r[2], r[3], r[5], f"{r[6]:.2f}", f"{r[7]:.2f}", _flagged_list(summary, task, r[2], r[3]),
                                  f"{r[9]:.2f}") for r in summary["share"] if r[1] == task and r[4] == "mean"],
                                numeric=(1, 2, 3, 4, 6)))
            lifts = [r for r in summary["lift"] if r[1] == task]
            if lifts:
                body.append(H.table(("camera", "layer", "mask", "steps", "lift", "lift, content only"),
                                    [(r[2], r[3], r[4], r[5], H.fmt(r[6], 2), H.fmt(r[7], 2)) for r in lifts],
                                    numeric=(1, 3, 4, 5)))
            body.append(plots.add(f"position_{H.anchor_id(task)[2:]}_{_label(run)}", figure(task, summary["maps"]),
                                  f"position-bound patches {task}",
                                  "Mean readout attention over the control steps per camera and layer, with the "
                                  "position-bound patches boxed, and the content-only view (attention minus the blank-"
                                  "frame map, clipped and renormalised) below it (tables/position_bound.csv)."))
    if not body:
        return ""
    intro = H.note(f"Runs with --attention-controls: each control step is asked again with every camera's frames "
                   f"blanked to their mean colour and mirrored left-right. A patch is position-bound (flagged) when it "
                   f"is hot (at least {Q.HOT:g}x the camera's mean patch attention), keeps at least {Q.KEEP:.0%} of its "
                   f"attention on the blank frame and at least {Q.KEEP:.0%} in place on the mirrored frame. 'Remains "
                   "blank' = sum min(blank, real) / sum real; 'follows the mirror' = the same with the mirrored "
                   "attention read at the mirror-image patch. Tables: tables/position_*.csv.")
    return H.section("Position", intro + "".join(str(b) for b in body), anchor="position")


def markdown(runs) -> str:
    """Per run and task: share per camera and layer (head mean) with the flagged patches, and the lift with and
    without the positional part (EVAL.md, docs)."""
    lines = []
    for run in runs:
        summary = summarise(run)
        for task in dict.fromkeys(r[1] for r in summary["share"]):
            lines += [f"#### {task} ({_label(run)})", "", "| camera | layer | control steps | remains blank | follows "
                      "the mirror | flagged patches (row,col) | attention on flagged |", "|---|---:|---:|---:|---:|---|---:|"]
            lines += [f"| {r[2]} | {r[3]} | {r[5]} | {r[6]:.2f} | {r[7]:.2f} | {_flagged_list(summary, task, r[2], r[3])} "
                      f"| {r[9]:.2f} |" for r in summary["share"] if r[1] == task and r[4] == "mean"]
            lifts = [r for r in summary["lift"] if r[1] == task]
            if lifts:
                lines += ["", "| camera | layer | mask | steps | lift | lift, content only |", "|---|---:|---|---:|---:|---:|"]
                lines += [f"| {r[2]} | {r[3]} | {r[4]} | {r[5]} | {r[6]:.2f} | {r[7]:.2f} |" for r in lifts]
            lines += ["", sentence(task, summary), ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    """`python -m harness.report.position RUN... [--eval-md EVAL.md]`: the Position section alone (the tables), printed;
    with --eval-md also written there (harness.report.eval_md). `python -m harness.report.phases` writes both."""
    from harness.report.eval_md import section_main, tables_section

    return section_main(argv, "python -m harness.report.position", "Write the Position section of an EVAL.md.",
                        tables_section("## Position", markdown, "no run here has position rows: give runs made with "
                                       "--attention-controls blank,mirror"))


if __name__ == "__main__":
    raise SystemExit(main())

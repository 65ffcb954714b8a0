"""The comparison page: a CompareResult (+ the paired episodes' step-0 arrays) -> one self-contained HTML file.

Sections: verdict, success per task for both arms with intervals and the paired table, step-0 attention
divergence per layer (and per layer x head), divergence over the first steps, and step-0 overlays of both arms
side by side per task. Building blocks and style come from harness.report.html / figures (the run report's);
`step0_frames` optionally renders the step-0 camera frames (same seed -> the observation both arms saw).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from harness.analysis.compare_result import CompareResult, OutcomeBlock, PairDetail, Rate
from harness.analysis.protocol_fields import ATTENTION_NOTES
from harness.bounded import open_npz
from harness.measures.attention import camera_maps
from harness.files import all_or_none, atomic_write_json, write_atomic
from harness.octo.tokens import TokenMap
from harness.report import html as H
from harness.verdicts import EXIT_OK, GateVerdict, gate_exit_code
from harness.analysis.provenance import summary_points
from harness.report.compare_md import difference_label, pairs_cell, to_decide
from harness.report.figures import _figure, _png, overlay_grid, run_colours, success_chart

ARM_LABELS = ("baseline", "candidate")


def _step0_maps(episode_dir: str) -> tuple[TokenMap, dict[str, np.ndarray]] | None:
    """attention.npz -> (token map, {obs key: (layers, rows, cols)} head- and readout-mean step-0 maps)."""
    path = Path(episode_dir) / "attention.npz"
    if not path.is_file():
        return None
    with open_npz(path) as z:
        if "readout_attention" not in z.files or not z["readout_attention"].shape[0]:
            return None
        tokens = TokenMap.from_arrays(z)
        rows = z["readout_attention"][0].astype(np.float32).mean(axis=(1, 2))  # (layers, keys)
    return tokens, {obs: camera_maps(rows, tokens, obs) for _, obs, _, _ in tokens.image_groups}


def step0_frames(result: CompareResult, protocol_env: dict | None) -> dict[tuple[str, int], dict[str, np.ndarray]]:
    """{(task, seed): {obs key: (H, W, 3) uint8}} for the first pair of each task: the env reset with that seed
    under the runs' env options (imports the simulator; both arms saw this observation at step 0)."""
    import envs

    options = envs.EnvOptions.from_dict(protocol_env) if protocol_env else envs.EnvOptions()
    frames = {}
    conditions = result.grid.perturb if result.grid else {}
    for label, seed in _first_pairs(result):
        task, _, condition = label.partition(" / ")  # a grid comparison's cells are "<task> / <condition>"
        perturb = conditions.get(condition) if condition else result.perturb
        env = envs.make(task, options.replace(masks=False), perturb=perturb)  # the perturbed scene both arms saw
        try:
            obs, _ = env.reset(seed=int(seed))
            frames[(label, seed)] = {k: np.asarray(v) for k, v in obs.items() if np.ndim(v) == 3}
        finally:
            env.close()
    return frames


def _first_pairs(result: CompareResult) -> list[tuple[str, int]]:
    seen = {}
    for p in result.pair_details:
        seen.setdefault(p.task, p.seed)
    return list(seen.items())


def _js_by_layer(result: CompareResult) -> bytes | None:
    step0 = result.drift.step0
    series = [(task, block.js_layer) for task, block in step0.tasks.items() if block.js_layer is not None]
    if not series:
        return None
    fig = _figure(5.5, 3.0)
    ax = fig.add_subplot()
    for (task, values), colour in zip(series, run_colours(len(series))):
        ax.plot(np.arange(len(values)), values, marker="o", color=colour, label=task)
    ax.set_xticks(range(max(len(v) for _, v in series)))
    ax.set_xlabel("layer")
    ax.set_ylabel("step-0 JS divergence (bits)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _png(fig)


def _js_layer_head(result: CompareResult) -> bytes | None:
    matrix = result.drift.step0.overall.js_layer_head
    if matrix is None:
        return None
    matrix = np.asarray(matrix, float)
    fig = _figure(1.6 + 0.4 * matrix.shape[1], 1.0 + 0.32 * matrix.shape[0])
    ax = fig.add_subplot()
    im = ax.imshow(matrix, aspect="auto", cmap="viridis", vmin=0, interpolation="nearest")
    ax.set_xlabel("head")
    ax.set_ylabel("layer")
    ax.set_xticks(range(matrix.shape[1]))
    ax.set_yticks(range(matrix.shape[0]))
    fig.colorbar(im, ax=ax, label="JS (bits)")
    return _png(fig)


def _first_steps(result: CompareResult) -> bytes | None:
    steps = result.drift.first_steps
    if not steps:
        return None
    fig = _figure(7.0, 2.6)
    x = [s.step for s in steps]
    for i, (values, label) in enumerate((([s.js_mean for s in steps], "attention JS (bits)"),
                                         ([s.action_l2 for s in steps], "action chunk L2"))):
        ax = fig.add_subplot(1, 2, i + 1)
        y = [np.nan if v is None else v for v in values]
        ax.plot(x, y, marker="o", color=run_colours(2)[1])
        ax.set_xticks(x)
        ax.set_xlabel("step")
        ax.set_ylabel(label)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    return _png(fig)


def _outcome_rows(result: CompareResult):
    outcomes = result.outcomes
    blocks: list[tuple[str, OutcomeBlock]] = list(outcomes.tasks.items())
    blocks += [("pooled", outcomes.overall)] if len(outcomes.tasks) > 1 else []
    for name, b in blocks:
        yield [
            name, pairs_cell(b),
            _arm_cell(b.baseline),
            _arm_cell(b.candidate),
            H.fmt_ci(b.difference, *b.difference_ci),
            f"{H.fmt(b.mcnemar_p)} ({H.fmt(b.mcnemar_p_holm)})",
            H.Raw(f"<b>{H.esc(b.verdict)}</b>"),
            to_decide(b, "more pairs"),
        ]


def _points(rates: dict[str, Rate]) -> dict[str, tuple]:
    """{task: (rate, interval low, high, n)} of one arm, as success_chart draws them (NaN where a table has no pairs
    with an outcome, so no rate)."""
    return {task: tuple(np.nan if v is None else v for v in (r.rate, r.ci_low, r.ci_high, r.n))
            for task, r in rates.items()}


def _arm_cell(rate: Rate) -> str:
    errored = rate.errored or 0
    return H.fmt_ci(rate.rate, rate.ci_low, rate.ci_high) + (f" ({errored} errored)" if errored else "")


def _pair_outcome(pair: PairDetail, arm: str):
    """An arm's success in one pair, or "errored" (the episode raised: no outcome)."""
    success, status = ((pair.baseline_success, pair.baseline_status) if arm == "baseline" else
                       (pair.candidate_success, pair.candidate_status))
    return success if status == "ok" else "errored"


def _overlays(result: CompareResult, frames: dict) -> str:
    parts = []
    pair_dirs: dict[str, PairDetail] = {}
    for p in result.pair_details:
        pair_dirs.setdefault(p.task, p)
    for task, pair in pair_dirs.items():
        maps = [_step0_maps(pair.baseline_dir), _step0_maps(pair.candidate_dir)]
        if any(m is None for m in maps):
            note = pair.attention_note if pair.attention_note in ATTENTION_NOTES.values() else None  # no attention
            parts.append(H.section(task, H.note(note or "no step-0 attention arrays for this pair"), level=3))
            continue
        cams = [obs for obs in maps[0][1] if obs in maps[1][1]]
        frame_set = frames.get((task, pair.seed), {})
        cells = []
        for obs in cams:
            figures = []
            for label, (_, by_obs) in zip(ARM_LABELS, maps):
                layer_maps = by_obs[obs][:, None]  # (layers, 1, rows, cols)
                png = overlay_grid([frame_set.get(obs)], layer_maps, list(range(layer_maps.shape[0])), [0],
                                   f"{label}: {obs}")
                figures.append(H.image(png, f"{task} {label} {obs} step 0"))
            cells.append(H.Raw("<div class='videos'>" + "".join(figures) + "</div>"))
        caption = (f"seed {pair.seed}; head- and readout-mean attention at step 0, each cell coloured with its own "
                   "range" + ("" if frame_set else "; camera frame not rendered"))
        parts.append(H.section(task, "".join(cells) + H.note(caption), level=3))
    return "".join(parts)


def compare_page(result: CompareResult, frames: dict | None = None, markdown: str | None = None) -> str:
    """The whole HTML document for a comparison result (see module docstring)."""
    base, cand = result.baseline, result.candidate
    verdict = result.verdict
    body = [H.banner(f"Verdict: {verdict}", danger=gate_exit_code(verdict) != EXIT_OK)]  # fails the default gate
    body += [H.note(note) for note in result.outcomes.notes]
    for arm in (base, cand):
        if arm.random_weights:
            body.append(H.banner(f"{arm.run} uses RANDOM weights ({arm.model}): not a trained policy", danger=True))
    ident = result.identical
    body.append(H.note(f"{GateVerdict.IDENTICAL} check (atol {ident.atol:g}, {ident.steps_compared}): "
                       + ("every paired array and outcome is equal" if ident.identical else
                          f"{ident.pairs_identical}/{result.pairs} pairs identical; first difference: "
                          f"{ident.first_difference}")))
    if ident.derived_measures:
        body.append(H.note("Derived measures: " + ident.derived_measures.note))
    points = "".join(f"<li>{H.esc(point)}</li>" for point in summary_points(result.provenance.summary))
    body.append(H.Raw(f"<div class='note'>Provenance:<ul>{points}</ul></div>"))

    colours = run_colours(2)
    tasks = list(result.outcomes.tasks)
    blocks = result.outcomes.tasks
    series = [(f"baseline: {base.run}", colours[0], _points({t: b.baseline for t, b in blocks.items()})),
              (f"candidate: {cand.run}", colours[1], _points({t: b.candidate for t, b in blocks.items()}))]
    cfg = result.config
    outcome_body = (
        H.table(["task", "pairs", "baseline success", "candidate success", "difference = candidate - baseline",
                 "McNemar p (Holm)", "verdict", "to decide"], _outcome_rows(result), numeric=(1,))
        + H.note(f"Intervals: Wilson at {100 * (1 - cfg.alpha):g}% for each arm; for the paired difference "
                 f"{difference_label(result)} (1998, method 10). {GateVerdict.HELD} = the interval and an exact test "
                 f"rule out a drop larger than {cfg.max_drop:g}; {GateVerdict.SUSPECT} = the interval lies below 0 but "
                 "the exact McNemar test (after Holm) does not reject; n counts "
                 "pairs in which both arms ran to an outcome (errored pairs are left out and counted).")
        + H.image(success_chart(tasks, series), "success per task, both arms")
    )
    missing = result.missing_pairs
    if missing.candidate or missing.baseline:
        outcome_body += H.note(f"Left out: {len(missing.candidate)} pairs missing from the candidate, "
                               f"{len(missing.baseline)} from the baseline.")
    sections = [("outcomes", "Outcomes", outcome_body)]

    s0 = result.drift.step0.overall
    drift_body = H.key_values([
        ("pairs", s0.pairs),
        ("action chunk L2 (mean)", H.fmt(s0.action_l2)),
        ("action max |difference|", H.fmt(s0.action_max_abs)),
        ("attention JS, mean (bits)", H.fmt(s0.js_mean)),
    ] + [(f"target lift change, {obs}, per layer", ", ".join(H.fmt(float(v), 2) for v in change))
         for obs, change in s0.target_lift_change.items()])
    for png, alt in ((_js_by_layer(result), "step-0 JS per layer"), (_js_layer_head(result), "step-0 JS per layer and head")):
        if png is not None:
            drift_body += H.image(png, alt)
    drift_body += H.note(f"At step 0: {result.differs.drift_label}.")
    sections.append(("drift", "Step-0 drift", drift_body))

    whole = result.drift.whole_episode
    steps_body = (H.image(_first_steps(result), "divergence over the first steps") if result.drift.first_steps else "")
    steps_body += H.note(f"Whole episodes (confounded: trajectories diverge once actions differ): attention JS "
                         f"{H.fmt(whole.js_mean)}, action L2 {H.fmt(whole.action_l2)}.")
    sections.append(("steps", "Divergence over the first steps", steps_body))
    sections.append(("overlays", "Step-0 overlays", _overlays(result, frames or {})))

    pair_rows = [[p.task, p.seed, _pair_outcome(p, "baseline"), _pair_outcome(p, "candidate"), p.baseline_steps,
                  p.candidate_steps, H.fmt(p.step0_action_l2), H.fmt(p.step0_js_mean),
                  "yes" if p.identical else (p.difference or "no")] for p in result.pair_details]
    sections.append(("pairs", "Pairs", H.details(f"{len(pair_rows)} pairs", H.table(
        ["task", "seed", "baseline success", "candidate success", "baseline steps", "candidate steps",
         "step-0 action L2", "step-0 JS", "identical"], pair_rows, numeric=(1, 4, 5, 6, 7)))))
    runs = H.key_values([(f"{label} {k}", getattr(arm, k)) for label, arm in zip(ARM_LABELS, (base, cand))
                         for k in ("run", "path", "model", "status", "episodes", "errors", "git_commit", "arrays")])
    if markdown:
        runs += H.details("Markdown summary", f"<pre>{H.esc(markdown)}</pre>")
    sections.append(("runs", "Runs", runs))

    body_html = "".join(body) + "".join(H.section(title, content, anchor=a) for a, title, content in sections)
    return H.page(f"octo-harness compare: {verdict}", body_html,
                  subtitle=f"baseline {base.run} ({base.model}) vs candidate {cand.run} ({cand.model})",
                  toc=[(a, title) for a, title, _ in sections], footer="octo-harness compare")


def write_comparison(result: CompareResult, out_dir: str | Path, frames: dict | None = None,
                     exit_code: int | None = None) -> dict:
    """Write compare.json, compare.md and compare.html (each atomically) into out_dir; returns {name: path}."""
    from dataclasses import replace

    from harness.report.compare_md import markdown_summary

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    markdown = markdown_summary(result, exit_code)
    paths = {"json": out / "compare.json", "markdown": out / "compare.md", "html": out / "compare.html"}
    with all_or_none(*paths.values()):
        atomic_write_json(paths["json"], replace(result, exit_code=exit_code).to_json())
        write_atomic(paths["markdown"], lambda f: f.write(markdown.encode()))
        page = compare_page(result, frames, markdown)
        write_atomic(paths["html"], lambda f: f.write(page.encode()))
    return paths

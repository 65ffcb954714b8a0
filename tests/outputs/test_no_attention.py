"""Records without attention: a policy that gives none (harness.policies.Capabilities.attention False, as a served
one) runs end to end on the real robosuite Lift env, and everything downstream works on its runs.

The policies are real: a deterministic scripted policy computing its chunk from the observation's proprio, and the
reference fixture Octo checkpoint seen through a policy that drops its attention (same actions, no attention). Its
episode folders hold actions, rewards, frames in the MP4, metrics and attention.npz with step and phase only; the
report says in one line that the run has no attention; `compare` of such a run with itself, and of an Octo run with
the same Octo without attention, is IDENTICAL, and against an Octo run says what differs; `view` rebuilds its
recording; `replay` refuses it in one line.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from envs.options import EnvOptions
from harness.analysis.compare import compare_runs
from harness.octo import load_pretrained
from harness.outputs.writers import EpisodeWriter, OutputOptions
from harness.policies.base import Capabilities, Policy
from harness.policy import InferenceResult
from harness.records import EpisodeMeta, StepRecord
from harness.run import Protocol, execute
from harness.verdicts import GateVerdict

STEPS = 3
CHEAP = OutputOptions(png_every=0, video=False)


class _ProprioInference:
    """The scripted policy's batched inference: a chunk from the newest proprio of each request."""

    batch_size = 1
    dataset_key = None
    action_dim = 7
    probes: list = []

    def __init__(self, horizon: int):
        self.horizon = horizon

    def __call__(self, requests):
        results = []
        for request in requests:
            proprio = np.asarray(request.observation["proprio"][-1], np.float64)  # (8,)
            arm = np.clip(-0.5 * np.tanh(proprio[:6]), -0.3, 0.3)
            chunk = np.stack([np.concatenate([arm * (k + 1) / self.horizon, [1.0 - 0.1 * k]]) for k in range(self.horizon)])
            results.append(InferenceResult(chunk.astype(np.float32), None, None, 0.0))
        return results

    def warm_up(self, request) -> None:
        self([request])


class ProprioPolicy(Policy):
    """A deterministic scripted policy without attention: actions from the proprio, like a policy behind a server."""

    source = "scripted:proprio"
    capabilities = Capabilities(attention=False)
    window_size = 1
    action_horizon = 4
    action_dim = 7
    image_sizes = {"image_primary": (64, 64)}
    lowdim_sizes = {"proprio": 8}

    def inference(self, config):
        return _ProprioInference(self.action_horizon)


class _Stripped:
    """An Octo inference whose results lose their attention and token map (the actions are untouched)."""

    def __init__(self, inner):
        self.inner = inner

    def __call__(self, requests):
        return [dataclasses.replace(r, readout_attention=None, full_attention=None, tokens=None)
                for r in self.inner(requests)]

    def __getattr__(self, name):
        return getattr(self.inner, name)


class OctoWithoutAttention(Policy):
    """The same Octo checkpoint, its attention dropped: one deterministic policy, with and without attention."""

    capabilities = Capabilities(attention=False)

    def __init__(self, octo: Policy):
        self.octo = octo
        for name in ("source", "is_random", "window_size", "action_horizon", "action_dim", "image_sizes",
                     "lowdim_sizes", "goal_image_sizes", "takes_language", "dataset_statistics", "example_batch",
                     "checkpoint_dir", "text_tokenizer"):
            setattr(self, name, getattr(octo, name))

    def inference(self, config):
        return _Stripped(self.octo.inference(config))


@pytest.fixture(scope="module")
def runs(fixtures_dir, tmp_path_factory):
    from harness.policies import as_policy

    out = tmp_path_factory.mktemp("no_attention")
    octo = as_policy(load_pretrained(str(fixtures_dir / "tiny")))
    base = Protocol(model=str(fixtures_dir / "tiny"), tasks=("Lift",), episodes=2, max_steps=STEPS,
                    env=EnvOptions(masks=True, fast_render=True), outputs=CHEAP)
    made = {}
    for name, protocol, model in (
            ("scripted", base.replace(outputs=OutputOptions(rerun=True, record_inputs=True)), ProprioPolicy()),
            ("scripted_again", base.replace(outputs=OutputOptions()), ProprioPolicy()),
            ("octo", base, octo),
            ("octo_without", base.replace(outputs=OutputOptions(video=False)), OctoWithoutAttention(octo))):
        made[name] = execute(protocol, out, name, model=model, progress=False, preflight="off")
    return made


def test_a_run_without_attention_writes_everything_but_attention(runs):
    summary = runs["scripted"]
    assert [row.status for row in summary.rows] == ["ok", "ok"]
    folder = summary.run_dir / "Lift" / "episode_0"
    with np.load(folder / "attention.npz") as z:
        assert set(z.files) <= {"step", "phase", "phase_names"} and "step" in z.files  # no attention arrays
        assert z["step"].tolist() == list(range(STEPS))
    with np.load(folder / "actions.npz") as z:
        assert z["executed"].shape == (STEPS, 7) and z["predicted"].shape == (STEPS, 4, 7)
    with np.load(folder / "inputs.npz") as z:
        assert z["input/proprio"].shape == (STEPS, 8)
    assert not list(folder.glob("*.png"))
    assert (folder / "rollout.mp4").stat().st_size > 0 and (folder / "episode.rrd").stat().st_size > 0
    rows = [json.loads(line) for line in (folder / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == STEPS and not {"share", "entropy", "mask_mass"} & set(rows[0])
    episode = json.loads((folder / "episode.json").read_text())
    assert episode["attention"] is False and episode["layers"] is None and episode["keys"] is None
    assert episode["files"]["png_count"] == 0 and episode["files"]["video"] == "rollout.mp4"
    octo = json.loads((runs["octo"].run_dir / "Lift" / "episode_0" / "episode.json").read_text())
    assert "attention" not in octo and octo["layers"]  # an episode with attention is written as before


def test_the_mp4_shows_the_frames_without_overlay_panels(runs):
    import imageio.v3 as iio

    frames = iio.imread(runs["scripted"].run_dir / "Lift" / "episode_0" / "rollout.mp4")
    assert frames.shape[0] == STEPS
    assert frames.shape[1] == 272 and frames.shape[2] == 528  # one camera row: frame | captions, no layer strip


def test_the_report_renders_and_says_in_one_line_that_the_run_has_no_attention(runs, tmp_path):
    from harness.report.build import build_report

    result = build_report([runs["scripted"].run_dir, runs["octo"].run_dir], tmp_path / "report")
    html = result.html.read_text()
    assert "no attention in scripted: scripted (scripted:proprio) gives actions only" in html
    assert "not analysed" not in html and "could not be analysed" not in html


def test_compare_of_runs_without_attention_is_identical_and_says_so(runs, tmp_path):
    from harness.report.compare_html import write_comparison

    result = compare_runs(runs["scripted"].run_dir, runs["scripted_again"].run_dir)
    assert result.verdict == GateVerdict.IDENTICAL
    assert any(note.startswith("attention: neither run has attention") for note in result.outcomes.notes)
    paths = write_comparison(result, tmp_path / "cmp")
    assert "readout attention: not comparable (neither run has attention" in paths["markdown"].read_text()


def test_one_policy_with_and_without_attention_compares_identical(runs):
    result = compare_runs(runs["octo"].run_dir, runs["octo_without"].run_dir)
    assert result.verdict == GateVerdict.IDENTICAL, result.identical.first_difference
    assert result.one_side_measures.baseline == ("attention",)
    assert sum("attention only in the baseline" in note for note in result.outcomes.notes) == 1


def test_compare_against_an_octo_run_says_what_differs(runs, tmp_path):
    from harness.report.compare_html import write_comparison

    result = compare_runs(runs["octo"].run_dir, runs["scripted"].run_dir)
    assert result.verdict != GateVerdict.IDENTICAL
    assert "actions.npz" in result.identical.first_difference
    assert result.one_side_measures.baseline == ("attention",)
    assert result.drift.step0.overall.js_mean is None and result.drift.step0.overall.action_l2 > 0
    paths = write_comparison(result, tmp_path / "cmp")
    assert "only the baseline has attention" in paths["html"].read_text()


def test_view_rebuilds_and_replay_refuses_in_one_line(runs, tmp_path):
    from harness.gate.replay import ReplayInputError, replay_run
    from harness.gate.view import build_recording

    shown = build_recording(runs["scripted_again"].run_dir, save=tmp_path / "ep.rrd", simulate=False)
    assert shown.source == "files" and (tmp_path / "ep.rrd").stat().st_size > 0
    with pytest.raises(ReplayInputError, match="a policy without attention") as error:
        replay_run(runs["scripted"].run_dir)
    assert "\n" not in str(error.value)


def test_the_writer_refuses_nothing_when_a_step_has_no_attention(tmp_path):
    meta = EpisodeMeta(run="test", task="Lift", episode=0, seed=7, instruction="lift", model="scripted:proprio",
                       model_is_random=False, dataset_key=None, text_tokenizer="none", execution="temporal_ensemble")
    rng = np.random.default_rng(0)
    with EpisodeWriter(tmp_path, None, meta, OutputOptions(png_every=1, video=True)) as writer:
        for t in range(2):
            writer.add_step(StepRecord(
                step=t, frames={"image_primary": rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)},
                readout_attention=None, actions_predicted=np.zeros((4, 7), np.float32),
                action_executed=np.zeros(7, np.float32), reward=0.0, success=False,
                masks={"image_primary": {"target": np.ones((64, 64), bool)}}))
    episode = json.loads((tmp_path / "episode.json").read_text())
    assert episode["attention"] is False and episode["steps"] == 2 and episode["files"]["video"] == "rollout.mp4"
    with np.load(tmp_path / "attention.npz") as z:
        assert z.files == ["step"]

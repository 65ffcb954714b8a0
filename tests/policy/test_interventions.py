"""Closed-loop interventions: parsing, what they do to the policy's inputs and actions, and runs that carry one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from harness.policies import as_policy
from harness.interventions import Intervention, parse_intervention
from harness.policy import EpisodeState, InferenceRequest, PolicyConfig, TaskPrompt

REFERENCE = Path(__file__).resolve().parents[2] / "models" / "octo-reference-robosuite"
CONFIG = PolicyConfig(dataset_key="robosuite_reference")


def test_parse_known_specs_and_canonical_strings():
    assert parse_intervention("mask-top:4:attention:2") == Intervention("mask-top", k=4, method="attention:2")
    assert parse_intervention("mask-top:4:attention").method == "attention:-1"
    assert parse_intervention("mask-bottom:3:saliency@image_wrist") == Intervention("mask-bottom", 3, "saliency", "image_wrist")
    assert parse_intervention("mask-random:5").spec() == "mask-random:5"
    assert parse_intervention("mask-all@image_primary").spec() == "mask-all@image_primary"
    assert parse_intervention("ablate-heads:2:3,0:1,2:3").spec() == "ablate-heads:0:1,2:3"
    for bad, message in [("mask-top:4", "needs a METHOD"), ("mask", "unknown intervention"), ("mask-top:x:saliency", "K must"),
                         ("mask-top:4:lime", "unknown method"), ("mask-top:4:random", "unknown method"),
                         ("ablate-heads:1", "LAYER:HEAD"), ("mask-all:3", "takes no K"),
                         ("mask-random:2:saliency", "takes no METHOD"), ("mask-top:2:saliency:1", "only attention")]:
        with pytest.raises(ValueError, match=message):
            PolicyConfig(intervention=bad)


def test_protocol_records_an_intervention_only_when_set():
    assert "intervention" not in PolicyConfig().to_dict()  # protocols without one keep their hash
    config = PolicyConfig(intervention="mask-top:4:attention")
    assert config.to_dict()["intervention"] == "mask-top:4:attention:-1"
    from harness.run.protocol import Protocol

    plain = Protocol(model="random:octo-small-1.5", tasks=("Lift",))
    masked = plain.replace(policy=config)
    assert plain.hash() != masked.hash()
    assert Protocol.from_dict(masked.to_dict()).policy.intervention == "mask-top:4:attention:-1"
    assert Protocol.from_dict(plain.to_dict()).policy.intervention is None


@pytest.fixture(scope="module")
def reference():
    from harness.octo import load_pretrained

    model = load_pretrained(str(REFERENCE))
    rng = np.random.default_rng(0)
    obs = {k: rng.integers(0, 255, (1, h, w, 3), dtype=np.uint8) for k, (h, w) in model.image_sizes.items()}
    obs["proprio"] = rng.standard_normal((1, 8)).astype(np.float32)
    obs["timestep_pad_mask"] = np.ones((1,), bool)
    obs["pad_mask_dict"] = {k: np.ones((1,), bool) for k in [*model.image_sizes, "proprio"]}
    return model, InferenceRequest(obs, TaskPrompt.of("lift the red cube"), 0, 0)


def _patch_grids(episode) -> dict[str, tuple[int, int]]:
    """{camera: (rows, cols)} of the model's patch grids, from the episode's stored token map."""
    with np.load(episode / "attention.npz") as tokens:
        return {str(k): tuple(int(x) for x in g) for k, g in zip(tokens["tokens/image_keys"], tokens["tokens/image_grids"])}


def _changed_patches(frame: np.ndarray, original: np.ndarray, patch: int = 16) -> set[int]:
    diff = (frame != original).any(axis=-1)
    rows = diff.shape[0] // patch
    return {r * rows + c for r in range(rows) for c in range(rows) if diff[r * patch:(r + 1) * patch, c * patch:(c + 1) * patch].any()}


def test_mask_all_and_head_ablation_change_the_reference_policy_measurably(reference):
    model, request = reference
    (plain,) = as_policy(model).inference(CONFIG)([request])
    (masked,) = as_policy(model).inference(PolicyConfig(dataset_key="robosuite_reference", intervention="mask-all"))([request])
    (ablated,) = as_policy(model).inference(PolicyConfig(dataset_key="robosuite_reference", intervention="ablate-heads:0:0,1:1"))([request])
    assert np.abs(masked.chunk - plain.chunk).max() > 0.05
    assert np.abs(ablated.chunk - plain.chunk).max() > 0.05
    assert ablated.observed is None
    for key, frame in masked.observed.items():  # the whole frame is its mean colour
        assert np.ptp(frame.reshape(-1, 3), axis=0).max() <= 1
    # the model itself is untouched by the ablation
    (again,) = as_policy(model).inference(CONFIG)([request])
    np.testing.assert_array_equal(again.chunk, plain.chunk)


@pytest.mark.slow
def test_mask_top_masks_the_k_patches_the_method_ranks_highest(reference):
    from harness.measures import attribution as A
    from harness.measures.faithfulness import ranking

    model, request = reference
    inference = as_policy(model).inference(PolicyConfig(dataset_key="robosuite_reference", intervention="mask-top:3:attention:2"))
    (result,) = inference([request])
    observations, tasks, keys = inference._inputs([request])
    analysis = A.analyse(A.OctoFunctions(model).at(observations, tasks, keys[0]), gradients=False)
    maps = A.attribute(analysis, "attention:2")
    for key in model.image_sizes:
        assert _changed_patches(result.observed[key], request.observation[key][-1]) == set(ranking(maps[key])[:3].tolist())
    bottom = as_policy(model).inference(PolicyConfig(dataset_key="robosuite_reference", intervention="mask-bottom:3:attention:2"))
    (low,) = bottom([request])
    for key in model.image_sizes:
        assert _changed_patches(low.observed[key], request.observation[key][-1]) == set(ranking(maps[key])[-3:].tolist())
    rand = as_policy(model).inference(PolicyConfig(dataset_key="robosuite_reference", intervention="mask-random:3@image_wrist"))
    (r1,), (r2,) = rand([request]), rand([request])
    assert set(r1.observed) == {"image_wrist"} and len(_changed_patches(r1.observed["image_wrist"], request.observation["image_wrist"][-1])) == 3
    np.testing.assert_array_equal(r1.observed["image_wrist"], r2.observed["image_wrist"])  # seeded by (seed, step)


def test_the_masked_frame_is_what_enters_the_history(reference):
    model, request = reference
    config = PolicyConfig(dataset_key="robosuite_reference", intervention="mask-all@image_primary")
    state = EpisodeState(model.image_sizes, 1, model.action_horizon, config, TaskPrompt.of("lift the red cube"), 0,
                         model.lowdim_sizes)
    obs = {k: v[0] for k, v in request.observation.items() if k.startswith("image_")}
    obs["proprio"] = request.observation["proprio"][0]
    decision = state.observe(obs)
    (result,) = as_policy(model).inference(config)([decision])
    state.complete(result)
    np.testing.assert_array_equal(state._history[-1]["image_primary"], result.observed["image_primary"])
    np.testing.assert_array_equal(state._history[-1]["image_wrist"], obs["image_wrist"])


def test_bad_intervention_for_the_model_is_one_line(reference):
    model, _ = reference
    for spec, message in [("ablate-heads:9:0", "outside the model's 4 layers x 4 heads"),
                          ("mask-all@image_side", "reads no camera 'image_side'"),
                          ("mask-top:2:attention:7", "layer 7 is outside")]:
        with pytest.raises(ValueError, match=message):
            as_policy(model).inference(PolicyConfig(dataset_key="robosuite_reference", intervention=spec))


@pytest.mark.slow
def test_intervention_runs_resume_and_compare_like_any_run(tmp_path, capsys):
    from harness import cli

    common = ["run", "--model", str(REFERENCE), "--task", "Lift", "--episodes", "2", "--max-steps", "4", "--fast-render",
              "--png-every", "0", "--no-video", "--out", str(tmp_path)]
    assert cli.main([*common, "--run-name", "plain"]) == 0
    assert cli.main([*common, "--run-name", "masked", "--intervene", "mask-top:4:attention:2"]) == 0
    manifest = json.loads((tmp_path / "masked" / "manifest.json").read_text())
    assert manifest["protocol"]["policy"]["intervention"] == "mask-top:4:attention:2"
    assert "intervention" not in json.loads((tmp_path / "plain" / "manifest.json").read_text())["protocol"]["policy"]
    before = (tmp_path / "masked" / "results.jsonl").read_text()
    assert cli.main([*common, "--run-name", "masked", "--intervene", "mask-top:4:attention:2"]) == 0  # resumes: nothing to run
    assert (tmp_path / "masked" / "results.jsonl").read_text() == before
    assert cli.main([*common, "--run-name", "masked", "--intervene", "mask-all"]) == 2  # another protocol under that name
    assert "policy.intervention" in capsys.readouterr().err
    code = cli.main(["compare", str(tmp_path / "plain"), str(tmp_path / "masked"), "--no-frames"])
    assert code in (0, 1)  # compared (not refused with 2)
    result = json.loads((tmp_path / "masked" / "compare_plain" / "compare.json").read_text())
    assert result["identical"]["pairs_identical"] == 0  # the intervention changed the actions
    plain = np.load(tmp_path / "plain" / "Lift" / "episode_0" / "actions.npz")["predicted"]
    masked = np.load(tmp_path / "masked" / "Lift" / "episode_0" / "actions.npz")["predicted"]
    assert np.abs(plain[0] - masked[0]).max() > 1e-3
    assert cli.main(["report", str(tmp_path / "plain"), str(tmp_path / "masked"), "--out", str(tmp_path / "report")]) == 0
    table = (tmp_path / "report" / "tables" / "interventions.csv").read_text().splitlines()
    assert len(table) == 2 and ",plain,mask-top:4:attention:2,Lift,2," in table[1]
    assert "Closed loop: interventions" in (tmp_path / "report" / "report.html").read_text()


@pytest.mark.slow
def test_attribution_and_faithfulness_in_a_run_leave_the_actions_alone(tmp_path):
    from harness import cli

    common = ["run", "--model", str(REFERENCE), "--task", "Lift", "--episodes", "1", "--max-steps", "6", "--fast-render",
              "--png-every", "0", "--no-video", "--out", str(tmp_path)]
    assert cli.main([*common, "--run-name", "plain"]) == 0
    assert cli.main([*common, "--run-name", "probed", "--faithfulness-every", "3", "--attribution", "attention:2,saliency"]) == 0
    episode = tmp_path / "probed" / "Lift" / "episode_0"
    plain = np.load(tmp_path / "plain" / "Lift" / "episode_0" / "actions.npz")["predicted"]
    np.testing.assert_array_equal(np.load(episode / "actions.npz")["predicted"], plain)  # measured beside, same actions
    maps = np.load(episode / "attribution.npz")
    assert list(maps["step"]) == list(range(6))
    assert maps["map/saliency/image_wrist"].shape == (6, 4, 4) and "map/random/image_primary" in maps  # wrist: 4x4
    rows = [json.loads(line) for line in (episode / "faithfulness.jsonl").read_text().splitlines()]
    assert sorted({r["step"] for r in rows}) == [0, 3]
    assert {(r["camera"], r["method"]) for r in rows} == {(c, m) for c in ("image_primary", "image_wrist")
                                                           for m in ("attention:2", "saliency", "random")}
    from harness.measures.faithfulness import _ks_with, k_values

    grids = _patch_grids(episode)
    for r in rows:
        n = int(np.prod(grids[r["camera"]]))  # 16 wrist patches; the primary camera's 64
        assert len(r["deletion_curve"]) == len(_ks_with(n, k_values(n), 17))
        assert r["deletion_curve"][0] == pytest.approx(0, abs=1e-5)
        assert r["deletion_curve"][-1] == pytest.approx(r["change_all"], rel=1e-3)
    policy = json.loads((tmp_path / "probed" / "manifest.json").read_text())["protocol"]["policy"]
    assert policy["faithfulness_every"] == 3 and policy["attribution"] == "attention:2,saliency"
    assert cli.main(["report", str(tmp_path / "probed"), "--out", str(tmp_path / "report")]) == 0
    table = (tmp_path / "report" / "tables" / "faithfulness.csv").read_text().splitlines()
    assert len(table) == 1 + 6  # 2 cameras x (attention:2, saliency, random)
    html = (tmp_path / "report" / "report.html").read_text()
    assert "Open loop: probed" in html and " ranks best, " in html
    # EVAL.md's Faithfulness section from the run, rendered from its figures file beside EVAL.md (issue 67 item 6)
    from harness.report import faithfulness, figures_file

    eval_md = tmp_path / "EVAL.md"
    assert faithfulness.main([str(tmp_path / "probed"), "--eval-md", str(eval_md)]) == 0
    doc = figures_file.read(tmp_path / "figures" / "faithfulness.json")
    assert eval_md.read_text().endswith(figures_file.render(doc)) and doc["section"] == "## Faithfulness"
    (table,) = [b["table"] for b in doc["blocks"] if "table" in b]
    assert len(table["rows"]) == 6 and table["header"][:3] == ["task", "camera", "method"]
    assert faithfulness.main([str(tmp_path / "plain"), "--eval-md", str(eval_md)]) == 2  # nothing to tabulate


def test_settings_and_protocol_files_carry_the_options(tmp_path):
    from harness.run.settings import build_protocol, read_protocol_file

    path = tmp_path / "eval.toml"
    path.write_text('task = "Lift"\nintervene = "mask-bottom:2:rollout@image_wrist"\nfaithfulness-every = 5\n'
                    'attribution = ["attention:1", "saliency"]\nfaithfulness-fill = "blur"\n')
    protocol = build_protocol({**read_protocol_file(path), "model": str(REFERENCE)})
    assert protocol.policy.intervention == "mask-bottom:2:rollout@image_wrist"
    assert (protocol.policy.faithfulness_every, protocol.policy.faithfulness_fill) == (5, "blur")
    assert protocol.policy.attribution == "attention:1,saliency"
    with pytest.raises(ValueError, match="faithfulness-every must be an integer >= 0"):
        PolicyConfig(faithfulness_every=-1)
    with pytest.raises(ValueError, match="unknown attribution method"):
        PolicyConfig(attribution="attention,lime")
    assert PolicyConfig(faithfulness_every=10).attribution == "attention,rollout,grad-attention,saliency"


def test_video_attention_takes_attribution_methods():
    from harness.outputs.writers import OutputOptions
    from harness.run.settings import build_protocol

    assert OutputOptions(video_attention="saliency").video_attention == "saliency"
    with pytest.raises(ValueError, match="grad-attention, saliency, occlusion"):
        OutputOptions(video_attention="lime")
    protocol = build_protocol({"task": ["Lift"], "model": str(REFERENCE), "video_attention": "occlusion"})
    assert protocol.policy.attribution == "occlusion"  # the maps the video shows are computed
    protocol = build_protocol({"task": ["Lift"], "model": str(REFERENCE), "video_attention": "saliency",
                               "faithfulness_every": 5})
    assert protocol.policy.attribution == "attention,rollout,grad-attention,saliency"


@pytest.mark.slow
def test_the_video_shows_an_attribution_map(tmp_path):
    from harness import cli

    assert cli.main(["run", "--model", str(REFERENCE), "--task", "Lift", "--episodes", "1", "--max-steps", "3",
                     "--fast-render", "--png-every", "2", "--layers", "2", "--video-attention", "grad-attention",
                     "--out", str(tmp_path), "--run-name", "v"]) == 0
    episode = tmp_path / "v" / "Lift" / "episode_0"
    info = json.loads((episode / "episode.json").read_text())
    assert info["success"] is not None
    # the PNG steps show the attribution maps too, every camera the model reads, beside the attention panels
    assert sorted(p.name for p in episode.glob("*.png")) == [
        "step_0000_attribution.png", "step_0000_layer_02.png", "step_0002_attribution.png", "step_0002_layer_02.png"]
    assert info["files"]["png_count"] == 4 and info["files"]["attribution_png_pattern"] == "step_{step:04d}_attribution.png"
    from PIL import Image

    panel = np.asarray(Image.open(episode / "step_0002_attribution.png"))
    assert panel.shape[0] > 2 * 128 and panel.std() > 10  # two camera rows of real frames
    assert (episode / "rollout.mp4").stat().st_size > 0
    grids = _patch_grids(episode)
    assert np.load(episode / "attribution.npz")["map/grad-attention/image_primary"].shape == (3, *grids["image_primary"])

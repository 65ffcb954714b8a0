"""--text-tokenizer auto|fallback|PATH: the CLI, protocol files and harness.toml choose it, the protocol records it,
and the tokenizer's identity (kind, vocabulary size, sha256) is part of the model fingerprint."""

import hashlib
import json
import shutil

import huggingface_hub.constants
import pytest
from tokenizers import Tokenizer, models, pre_tokenizers, processors

from harness.cli import build_parser, main
from harness.conventions import ConventionsError, CheckpointConventions
from harness.run.protocol import model_fingerprint
from harness.run.settings import build_protocol, read_protocol_file

T5_PROCESSOR = {"module": "octo.data.utils.text_processing", "name": "HFTokenizer", "args": [],
                "kwargs": {"tokenizer_name": "t5-base", "encode_with_model": False,
                           "tokenizer_kwargs": {"max_length": 16, "padding": "max_length", "truncation": True}}}


def toy_tokenizer(path, words):
    """A word-level tokenizer.json with T5's special ids (<pad> 0, </s> 1, <unk> 2), appending </s>."""
    vocab = {"<pad>": 0, "</s>": 1, "<unk>": 2, **{w: i + 3 for i, w in enumerate(words)}}
    tok = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.post_processor = processors.TemplateProcessing(single="$A </s>", special_tokens=[("</s>", 1)])
    path.parent.mkdir(parents=True, exist_ok=True)
    tok.save(str(path))
    return path


@pytest.fixture()
def empty_hf_cache(tmp_path, monkeypatch):
    cache = tmp_path / "hf-cache"
    cache.mkdir()
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(cache))
    return cache


def cache_t5_base(cache, tokenizer_json):
    """Place a tokenizer.json as google-t5/t5-base in a Hugging Face cache (the hub's folder layout)."""
    repo = cache / "models--google-t5--t5-base"
    snapshot = repo / "snapshots" / ("0" * 40)
    snapshot.mkdir(parents=True, exist_ok=True)
    shutil.copy(tokenizer_json, snapshot / "tokenizer.json")
    (repo / "refs").mkdir(exist_ok=True)
    (repo / "refs" / "main").write_text("0" * 40)


@pytest.fixture()
def t5_checkpoint(fixtures_dir, tmp_path):
    """The tiny fixture with a config naming the t5-base text processor, as every released Octo 1.5 model does."""
    ckpt = tmp_path / "ckpt"
    shutil.copytree(fixtures_dir / "tiny", ckpt)
    config = json.loads((ckpt / "config.json").read_text())
    config["text_processor"] = T5_PROCESSOR
    (ckpt / "config.json").write_text(json.dumps(config))
    return ckpt


def test_run_and_regress_take_text_tokenizer():
    parser = build_parser()
    run = parser.parse_args(["run", "--text-tokenizer", "fallback"])
    assert run.text_tokenizer == "fallback"
    reg = parser.parse_args(["regress", "--baseline", "b", "--model", "m", "--text-tokenizer", "/x/tokenizer.json"])
    assert reg.text_tokenizer == "/x/tokenizer.json"


def test_protocol_records_the_choice_and_auto_keeps_the_old_hash(tmp_path):
    toy = toy_tokenizer(tmp_path / "tok" / "tokenizer.json", ["pick", "up"])
    auto = build_protocol({"task": ["Lift"], "model": "random:octo-small-1.5", "text_tokenizer": "auto"})
    plain = build_protocol({"task": ["Lift"], "model": "random:octo-small-1.5"})
    assert auto.text_tokenizer is None and "text_tokenizer" not in auto.to_dict() and auto.hash() == plain.hash()
    fallback = build_protocol({"task": ["Lift"], "model": "random:octo-small-1.5", "text_tokenizer": "fallback"})
    assert fallback.to_dict()["text_tokenizer"] == "fallback" and fallback.hash() != plain.hash()
    path = build_protocol({"task": ["Lift"], "model": "random:octo-small-1.5", "text_tokenizer": str(toy.parent)})
    assert path.text_tokenizer == str(toy.parent.resolve())
    assert type(path).from_dict(path.to_dict()).text_tokenizer == path.text_tokenizer
    with pytest.raises(FileNotFoundError, match="--text-tokenizer"):
        build_protocol({"task": ["Lift"], "model": "random:octo-small-1.5", "text_tokenizer": "./missing.json"})


def test_protocol_file_path_is_relative_to_the_file(tmp_path):
    toy = toy_tokenizer(tmp_path / "tok" / "tokenizer.json", ["pick"])
    (tmp_path / "eval.toml").write_text('task = "Lift"\ntext-tokenizer = "tok/tokenizer.json"\n')
    settings = read_protocol_file(tmp_path / "eval.toml")
    assert build_protocol(settings).text_tokenizer == str(toy.resolve())


def test_harness_toml_text_tokenizer(tmp_path):
    toy = toy_tokenizer(tmp_path / "ckpt" / "mytok" / "tokenizer.json", ["pick"])
    (tmp_path / "ckpt" / "harness.toml").write_text('format = "octo-harness-conventions/1"\n[text]\ntokenizer = "mytok"\n')
    conventions = CheckpointConventions.read(tmp_path / "ckpt")
    assert conventions.text_tokenizer == str(toy.parent.resolve())
    assert CheckpointConventions.parse({"text": {"tokenizer": "fallback"}}).to_toml().count('tokenizer = "fallback"') == 1
    (tmp_path / "ckpt" / "harness.toml").write_text('[text]\ntokenizer = "nope"\n')
    with pytest.raises(ConventionsError, match="does not exist"):
        CheckpointConventions.read(tmp_path / "ckpt")
    with pytest.raises(ConventionsError, match=r"\[text\]"):
        CheckpointConventions.parse({"text": {"name": "x"}})


def test_fingerprint_tells_tokenizers_apart(t5_checkpoint, empty_hf_cache, tmp_path):
    a = toy_tokenizer(tmp_path / "a" / "tokenizer.json", ["pick", "up"])
    b = toy_tokenizer(tmp_path / "b" / "tokenizer.json", ["pick", "up", "the"])
    fallback_fp, details = model_fingerprint(str(t5_checkpoint), "fallback")
    assert details["tokenizer"]["kind"] == "fallback-hash" and details["tokenizer"]["sha256"] is None
    fp_a, details_a = model_fingerprint(str(t5_checkpoint), str(a))
    assert details_a["tokenizer"]["sha256"] == hashlib.sha256(a.read_bytes()).hexdigest()
    assert details_a["tokenizer"]["vocab_size"] == 5
    fp_b, _ = model_fingerprint(str(t5_checkpoint), str(b))
    assert len({fallback_fp, fp_a, fp_b}) == 3
    # a toy t5-base in a throw-away cache and another one: the automatic choice is told apart too
    cache_t5_base(empty_hf_cache, a)
    auto_a, auto_details = model_fingerprint(str(t5_checkpoint))
    assert auto_details["tokenizer"]["name"] == "t5-base" and auto_details["tokenizer"]["sha256"] == details_a["tokenizer"]["sha256"]
    cache_t5_base(empty_hf_cache, b)
    auto_b, _ = model_fingerprint(str(t5_checkpoint))
    assert auto_a != auto_b
    # a random preset: the fallback offline, the cached file otherwise
    assert model_fingerprint("random:octo-small-1.5", "fallback")[0] == "preset:octo-small-1.5+fallback-hash:32128"
    assert model_fingerprint("random:octo-small-1.5")[0].startswith("preset:octo-small-1.5+tokenizer.json:")


def test_tokenizer_inside_the_checkpoint_keeps_its_fingerprint(fixtures_dir, tmp_path):
    """The reference policy's tokenizer folder is one of the checkpoint files: no extra line (baselines keep their
    fingerprint), and editing the tokenizer changes it through the files."""
    from pathlib import Path

    reference = Path(__file__).resolve().parents[2] / "models" / "octo-reference-robosuite"
    fp, details = model_fingerprint(str(reference))
    assert details["tokenizer"]["path"].startswith(str(reference)) and "tokenizer/tokenizer.json" in details["files"]
    baseline = Path(__file__).resolve().parents[2] / "results" / "baselines" / "reference-lift" / "manifest.json"
    if baseline.is_file():
        recorded = json.loads(baseline.read_text())["protocol"]["model_fingerprint"]
        assert fp == recorded


@pytest.mark.slow
def test_cli_offline_t5_checkpoint_names_the_option_then_runs_with_it(t5_checkpoint, empty_hf_cache, tmp_path, capsys):
    common = ["run", "--model", str(t5_checkpoint), "--task", "Lift", "--max-steps", "2", "--png-every", "0",
              "--no-video", "--no-masks", "--fast-render", "--out", str(tmp_path / "runs")]
    assert main([*common, "--run-name", "auto"]) == 2
    err = capsys.readouterr().err
    assert "--text-tokenizer" in err and "text_tokenizer='fallback'" not in err.replace("text_tokenizer= in Python", "")
    assert not (tmp_path / "runs" / "auto").exists()

    toy = toy_tokenizer(tmp_path / "tok" / "tokenizer.json", ["lift", "the", "red", "cube"])
    assert main([*common, "--run-name", "toy", "--text-tokenizer", str(toy)]) == 0
    run = tmp_path / "runs" / "toy"
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["protocol"]["text_tokenizer"] == str(toy.resolve())
    identity = manifest["model"]["tokenizer"]
    assert identity["kind"] == "tokenizer.json" and identity["vocab_size"] == 7
    assert identity["sha256"] == hashlib.sha256(toy.read_bytes()).hexdigest()
    episode = json.loads((run / "Lift" / "episode_0" / "episode.json").read_text())
    assert identity["sha256"][:12] in json.dumps(episode) and "7 ids" in json.dumps(episode)
    assert manifest["protocol"]["model_fingerprint"] != model_fingerprint(str(t5_checkpoint), "fallback")[0]

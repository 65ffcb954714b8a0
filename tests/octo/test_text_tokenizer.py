"""Text tokenizer: T5 padding/truncation semantics, local and cached-hub loading, offline errors, fallback."""

import logging

import huggingface_hub.constants
import numpy as np
import pytest
from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors

from harness.octo.text import (
    FALLBACK_NAME,
    TokenizerUnavailableError,
    fallback_tokenizer,
    load_text_tokenizer,
    pad_and_truncate,
)

# sentencepiece-style pieces with log-probability scores, T5's special ids first
PIECES = [
    ("<pad>", 0.0), ("</s>", 0.0), ("<unk>", 0.0),
    ("▁pick", -2.0), ("▁up", -2.0), ("▁the", -2.0), ("▁red", -3.0), ("▁block", -3.0),
    ("▁put", -3.0), ("▁on", -3.0), ("s", -4.0), ("▁", -5.0), ("▁bl", -6.0), ("ock", -6.0),
]  # ids 0..13


@pytest.fixture()
def tokenizer_json(tmp_path):
    tok = Tokenizer(models.Unigram(PIECES, unk_id=2))
    tok.pre_tokenizer = pre_tokenizers.Metaspace(replacement="▁", prepend_scheme="always")
    tok.decoder = decoders.Metaspace(replacement="▁", prepend_scheme="always")
    tok.post_processor = processors.TemplateProcessing(single="$A </s>", special_tokens=[("</s>", 1)])
    tok.add_special_tokens(["<pad>", "</s>", "<unk>"])
    path = tmp_path / "tok" / "tokenizer.json"
    path.parent.mkdir()
    tok.save(str(path))
    return path


@pytest.fixture()
def offline_empty_cache(tmp_path, monkeypatch):
    """HF_HUB_OFFLINE on (also the constant huggingface_hub read at import) and an empty cache."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    cache = tmp_path / "hf-cache"
    cache.mkdir()
    return cache


def test_known_sentence_exact_ids_and_padding(tokenizer_json):
    tok = load_text_tokenizer(str(tokenizer_json))
    assert not tok.is_fallback and tok.max_length == 16
    out = tok.encode(["pick up the red blocks", "put on"])
    assert set(out) == {"input_ids", "attention_mask"}
    for arr in out.values():
        assert arr.shape == (2, 16) and arr.dtype == np.int32
    want_0 = [3, 4, 5, 6, 7, 10, 1] + [0] * 9  # ▁block + s, then </s>, then padding
    want_1 = [8, 9, 1] + [0] * 13
    assert out["input_ids"].tolist() == [want_0, want_1]
    assert out["attention_mask"].tolist() == [[1] * 7 + [0] * 9, [1] * 3 + [0] * 13]


def test_folder_path_loads_its_tokenizer_json(tokenizer_json):
    ids = load_text_tokenizer(str(tokenizer_json.parent)).encode(["the"])["input_ids"]
    assert ids[0, :3].tolist() == [5, 1, 0]


def test_truncation_keeps_eos_last(tokenizer_json):
    tok = load_text_tokenizer(str(tokenizer_json), max_length=16)
    out = tok.encode([" ".join(["red"] * 30)])
    assert out["input_ids"].tolist() == [[6] * 15 + [1]]
    assert out["attention_mask"].tolist() == [[1] * 16]
    short = load_text_tokenizer(str(tokenizer_json), max_length=4).encode(["pick up the red block"])
    assert short["input_ids"].tolist() == [[3, 4, 5, 1]]


def test_empty_batch_and_single_string_misuse(tokenizer_json):
    tok = load_text_tokenizer(str(tokenizer_json))
    assert tok.encode([])["input_ids"].shape == (0, 16)
    with pytest.raises(TypeError, match="wrap a single string in a list"):
        tok.encode("pick up the red block")


def test_missing_local_file_is_one_clear_error(tmp_path):
    with pytest.raises(TokenizerUnavailableError, match="does not exist; pass an existing tokenizer.json"):
        load_text_tokenizer(str(tmp_path / "nope" / "tokenizer.json"))
    with pytest.raises(TokenizerUnavailableError, match="no tokenizer.json in"):
        load_text_tokenizer(str(tmp_path))


def test_offline_without_cache_names_the_fix(offline_empty_cache):
    with pytest.raises(TokenizerUnavailableError) as e:
        load_text_tokenizer("t5-base", cache_dir=offline_empty_cache)
    msg = str(e.value)
    assert msg == (
        "t5-base tokenizer not in the Hugging Face cache and HF_HUB_OFFLINE=1; "
        "run once online or pass a local tokenizer.json"
    )
    assert isinstance(e.value, FileNotFoundError)


def test_offline_hub_name_resolves_from_cache(offline_empty_cache, tokenizer_json):
    # the hub cache layout: models--<org>--<name>/{refs/main, snapshots/<commit>/<file>}
    commit = "0123456789abcdef0123456789abcdef01234567"
    repo_dir = offline_empty_cache / "models--google-t5--t5-base"
    (repo_dir / "refs").mkdir(parents=True)
    (repo_dir / "refs" / "main").write_text(commit)
    snapshot = repo_dir / "snapshots" / commit
    snapshot.mkdir(parents=True)
    (snapshot / "tokenizer.json").write_bytes(tokenizer_json.read_bytes())
    tok = load_text_tokenizer("t5-base", cache_dir=offline_empty_cache)
    assert tok.name == "t5-base" and not tok.is_fallback
    assert tok.encode(["pick up"])["input_ids"][0, :3].tolist() == [3, 4, 1]


def test_offline_fallback_is_deterministic_and_labelled(offline_empty_cache, caplog):
    with caplog.at_level(logging.WARNING, logger="harness.octo.text"):
        tok = load_text_tokenizer("t5-base", allow_fallback=True, vocab_size=100, cache_dir=offline_empty_cache)
    assert tok.is_fallback and tok.name == FALLBACK_NAME == "fallback-hash (not T5)"
    assert any("fallback" in r.getMessage() and "t5-base" in r.getMessage() for r in caplog.records)
    texts = ["Pick up the red block.", "pick UP the red block", "open the drawer"]
    out = tok.encode(texts)
    again = fallback_tokenizer(100).encode(texts)
    np.testing.assert_array_equal(out["input_ids"], again["input_ids"])
    ids, mask = out["input_ids"], out["attention_mask"]
    assert ids.shape == (3, 16) and ids.dtype == np.int32
    assert ids[0].tolist() == ids[1].tolist()  # case and punctuation do not matter
    assert ids[0, 5] == 1 and (ids[0, 6:] == 0).all() and (ids[0, :5] >= 3).all() and (ids[0, :5] < 100).all()
    assert mask[0].tolist() == [1] * 6 + [0] * 10
    assert ids[2, :3].tolist() != ids[0, :3].tolist()
    # pinned value: crc32(b"pick") == 0x99CD0F9B; the mapping must never drift between runs or machines
    assert fallback_tokenizer(32128).encode(["pick"])["input_ids"][0, :2].tolist() == [3 + 0x99CD0F9B % 32125, 1]


def test_fallback_truncation_and_bad_vocab():
    out = fallback_tokenizer(50, max_length=4).encode(["a b c d e f"])
    assert out["input_ids"][0, 3] == 1 and out["attention_mask"].tolist() == [[1, 1, 1, 1]]
    with pytest.raises(ValueError, match="vocab_size > 3"):
        fallback_tokenizer(3)


def test_pad_and_truncate_hand_values():
    enc = pad_and_truncate([[5, 6], [], [7, 8, 9, 10]], max_length=4)
    assert enc.input_ids.tolist() == [[5, 6, 1, 0], [1, 0, 0, 0], [7, 8, 9, 1]]
    assert enc.attention_mask.tolist() == [[1, 1, 1, 0], [1, 0, 0, 0], [1, 1, 1, 1]]


def test_cache_only_never_contacts_the_hub(tmp_path, monkeypatch):
    import socket

    import huggingface_hub.constants as hf_constants

    from harness.octo.text import load_text_tokenizer

    monkeypatch.setattr(hf_constants, "HF_HUB_OFFLINE", False)  # as on a machine with no offline flag set
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    lookups = []

    def no_network(*args, **kwargs):
        lookups.append(args[0] if args else kwargs)
        raise OSError("network disabled in this test")

    monkeypatch.setattr(socket, "getaddrinfo", no_network)
    tok = load_text_tokenizer("t5-base", allow_fallback=True, cache_only=True, cache_dir=tmp_path)
    assert tok.is_fallback and lookups == []

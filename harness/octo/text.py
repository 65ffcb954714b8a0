"""Text tokenizer for Octo's language tasks: instruction strings -> fixed-length T5 token ids and mask.

Matches Octo's HFTokenizer (Hugging Face's t5-base tokenizer called with max_length=16,
padding="max_length", truncation=True): ids end with `</s>` (id 1), padding id 0 follows, the attention
mask is 1 for real tokens including `</s>`, and truncation keeps `</s>` as the last token.

The tokenizer comes from a local `tokenizer.json` (or a folder holding one), or from the Hugging Face hub
or cache (honours HF_HUB_OFFLINE). Where no tokenizer can be had offline, callers running a randomly
initialised model may ask for a deterministic hash-based fallback, which is labelled as not being T5.
"""

from __future__ import annotations

import hashlib
import logging
import re
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tokenizers
from huggingface_hub import constants as hf_constants
from huggingface_hub import hf_hub_download
from huggingface_hub.utils import (
    EntryNotFoundError,
    HFValidationError,
    LocalEntryNotFoundError,
    OfflineModeIsEnabled,
    RepositoryNotFoundError,
    RevisionNotFoundError,
)

log = logging.getLogger(__name__)

FALLBACK_NAME = "fallback-hash (not T5)"
EOS_ID = 1  # `</s>` in every T5 vocabulary
PAD_ID = 0  # `<pad>`
_FIRST_WORD_ID = 3  # after <pad>, </s>, <unk>
_TOKENIZER_FILE = "tokenizer.json"
# Legacy short names of the original T5 checkpoints, now under the google-t5 organisation on the hub.
_LEGACY_HUB_NAMES = {n: f"google-t5/{n}" for n in ("t5-small", "t5-base", "t5-large", "t5-3b", "t5-11b")}


class TokenizerUnavailableError(FileNotFoundError):
    """The requested tokenizer is neither on disk nor obtainable from the Hugging Face hub or cache."""


@dataclass(frozen=True)
class EncodedText:
    input_ids: np.ndarray  # (batch, max_length) int32
    attention_mask: np.ndarray  # (batch, max_length) int32, 1 for real tokens incl. </s>

    def as_dict(self) -> dict[str, np.ndarray]:
        return {"input_ids": self.input_ids, "attention_mask": self.attention_mask}


@dataclass(frozen=True, eq=False)
class TextTokenizer:
    """Encodes instructions to (batch, max_length) arrays.

    `tokenizer` is a `tokenizers.Tokenizer` already set to truncate and pad to `max_length` (see
    `load_text_tokenizer`); None means the hash fallback over `fallback_vocab_size` ids. `path` and `sha256`
    name the tokenizer.json it was read from.
    """

    name: str
    max_length: int
    tokenizer: tokenizers.Tokenizer | None
    fallback_vocab_size: int = 0
    path: str | None = None
    sha256: str | None = None

    @property
    def is_fallback(self) -> bool:
        return self.tokenizer is None

    @property
    def vocab_size(self) -> int:
        return self.fallback_vocab_size if self.tokenizer is None else int(self.tokenizer.get_vocab_size())

    def identity(self) -> dict:
        """What tells two tokenizers apart: kind ("tokenizer.json" | "fallback-hash"), name, vocabulary size,
        max length and the sha256 of the file (None for the fallback)."""
        return {"kind": "fallback-hash" if self.is_fallback else "tokenizer.json", "name": self.name,
                "vocab_size": self.vocab_size, "max_length": self.max_length, "sha256": self.sha256, "path": self.path}

    def label(self) -> str:
        """One line for records: 't5-base [tokenizer.json, 32100 ids, sha256 1a2b3c4d5e6f]' or the fallback's."""
        if self.is_fallback:
            return f"{self.name} [fallback tokenizer, {self.vocab_size} ids]"
        return f"{self.name} [tokenizer.json, {self.vocab_size} ids, sha256 {(self.sha256 or '?')[:12]}]"

    def encode(self, texts: Sequence[str]) -> dict[str, np.ndarray]:
        """{"input_ids", "attention_mask"}: (batch, max_length) int32 each."""
        if isinstance(texts, str):
            raise TypeError("TextTokenizer.encode takes a list of instructions; wrap a single string in a list")
        texts = list(texts)
        if self.tokenizer is None:
            ids = [hash_word_ids(t, self.fallback_vocab_size) for t in texts]
            return pad_and_truncate(ids, self.max_length).as_dict()
        encodings = self.tokenizer.encode_batch(texts) if texts else []
        shape = (len(texts), self.max_length)
        input_ids = np.array([e.ids for e in encodings], np.int32).reshape(shape)
        attention_mask = np.array([e.attention_mask for e in encodings], np.int32).reshape(shape)
        return EncodedText(input_ids, attention_mask).as_dict()


def hash_word_ids(text: str, vocab_size: int) -> list[int]:
    """Ids in [3, vocab_size) for the lower-cased words of `text`, via CRC32 (stable across runs and machines)."""
    words = re.findall(r"\w+", text.lower())
    span = vocab_size - _FIRST_WORD_ID
    return [_FIRST_WORD_ID + zlib.crc32(w.encode("utf-8")) % span for w in words]


def pad_and_truncate(ids: Sequence[Sequence[int]], max_length: int) -> EncodedText:
    """Appends </s> to each id list, truncating first so </s> stays last, then pads with 0 to max_length."""
    input_ids = np.full((len(ids), max_length), PAD_ID, np.int32)  # (batch, max_length)
    attention_mask = np.zeros((len(ids), max_length), np.int32)
    for row, seq in enumerate(ids):
        seq = [*seq[: max_length - 1], EOS_ID]
        input_ids[row, : len(seq)] = seq
        attention_mask[row, : len(seq)] = 1
    return EncodedText(input_ids, attention_mask)


def fallback_tokenizer(vocab_size: int, max_length: int = 16) -> TextTokenizer:
    """Deterministic word-hash tokenizer for models without a real one; its ids mean nothing to T5."""
    if vocab_size <= _FIRST_WORD_ID:
        raise ValueError(f"fallback tokenizer needs vocab_size > {_FIRST_WORD_ID}, got {vocab_size}")
    _check_max_length(max_length)
    return TextTokenizer(FALLBACK_NAME, max_length, None, vocab_size)


def load_text_tokenizer(
    name: str = "t5-base",
    max_length: int = 16,
    *,
    allow_fallback: bool = False,
    vocab_size: int = 32128,
    cache_dir: str | Path | None = None,
    cache_only: bool = False,
    warn: bool = True,
) -> TextTokenizer:
    """Tokenizer from a local tokenizer.json / folder, or a hub repo ("t5-base" -> google-t5/t5-base).

    Offline without a cached copy: the fallback over `vocab_size` ids if `allow_fallback`, else
    TokenizerUnavailableError. `cache_dir` overrides the Hugging Face cache location; `cache_only`
    never contacts the hub (as if offline), for callers that would rather fall back than wait. `warn`:
    log the fallback (off where the same tokenizer is only being identified, before loading).
    """
    _check_max_length(max_length)
    path = _local_tokenizer_file(name)
    if path is None:
        try:
            path = _download(name, cache_dir, cache_only)
        except TokenizerUnavailableError:
            if not allow_fallback:
                raise
            if warn:
                log.warning("%s tokenizer unavailable offline; using the deterministic %s tokenizer", name, FALLBACK_NAME)
            return fallback_tokenizer(vocab_size, max_length)
    return TextTokenizer(name, max_length, _configured(path, max_length), path=str(path), sha256=_sha256(path))


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _check_max_length(max_length: int) -> None:
    if max_length < 1:
        raise ValueError(f"max_length must be at least 1 (room for </s>), got {max_length}")


def _local_tokenizer_file(name: str) -> Path | None:
    """The tokenizer.json `name` points to on disk; None if `name` is a hub repo name."""
    path = Path(name).expanduser()
    if path.is_file():
        return path
    if path.is_dir():
        if not (path / _TOKENIZER_FILE).is_file():
            raise TokenizerUnavailableError(
                f"no {_TOKENIZER_FILE} in {path}; pass a folder holding one or the file itself"
            )
        return path / _TOKENIZER_FILE
    if name.endswith(".json") or name.startswith(("/", ".", "~")):
        raise TokenizerUnavailableError(f"tokenizer file {path} does not exist; pass an existing tokenizer.json")
    return None


def _download(name: str, cache_dir: str | Path | None, cache_only: bool = False) -> Path:
    repo = _LEGACY_HUB_NAMES.get(name, name)
    try:
        return Path(hf_hub_download(repo, _TOKENIZER_FILE, cache_dir=cache_dir, local_files_only=cache_only))
    except (LocalEntryNotFoundError, OfflineModeIsEnabled) as e:  # before EntryNotFoundError: a subclass of it
        if hf_constants.HF_HUB_OFFLINE:
            where = "HF_HUB_OFFLINE=1"
        else:
            where = "the cache alone was searched" if cache_only else "the hub could not be reached"
        raise TokenizerUnavailableError(
            f"{name} tokenizer not in the Hugging Face cache and {where}; "
            "run once online or pass a local tokenizer.json"
        ) from e
    except (RepositoryNotFoundError, RevisionNotFoundError, EntryNotFoundError, HFValidationError) as e:
        raise TokenizerUnavailableError(
            f"no {_TOKENIZER_FILE} in hub repo {repo!r}; pass a hub repo that has one or a local tokenizer.json"
        ) from e


def _configured(path: Path, max_length: int) -> tokenizers.Tokenizer:
    """Loads tokenizer.json and sets right-side truncation and padding to exactly max_length."""
    try:
        tok = tokenizers.Tokenizer.from_file(str(path))
    except Exception as e:  # the Rust side raises a bare Exception for malformed files
        raise ValueError(f"{path} is not a valid tokenizer.json ({e}); pass a Hugging Face tokenizers file") from e
    pad_id = tok.token_to_id("<pad>")
    if pad_id is None:
        raise ValueError(f"{path} has no <pad> token; pass a T5 tokenizer.json")
    tok.enable_truncation(max_length=max_length, direction="right")
    tok.enable_padding(direction="right", pad_id=pad_id, pad_token="<pad>", length=max_length)
    return tok

"""An Octo checkpoint's fingerprint, from its files (stream-hashed; a hub model from the local cache), before it loads.

The protocol records it (`model_fingerprint`): a changed file or tokenizer is another model, whatever its path.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from harness.files import FIGURES_FOLDER


def _sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def files_fingerprint(root: Path, files: list[Path]) -> tuple[str, dict]:
    entries = {}
    for path in sorted(files):
        resolved = path.resolve()  # hub snapshots are symlinks into the blob store
        entries[path.relative_to(root).as_posix()] = {"size": resolved.stat().st_size, "sha256": _sha256_file(resolved)}
    lines = "".join(f"{name} {e['size']} {e['sha256']}\n" for name, e in entries.items())
    return "sha256:" + hashlib.sha256(lines.encode()).hexdigest(), entries


def checkpoint_files(ckpt: Path, step: int | None) -> list[Path]:
    """The files loading reads: config.json, dataset_statistics.json, example_batch.msgpack, every file of the
    chosen step folder (latest when `step` is None), and the files of non-step subfolders (tokenizer, T5 config),
    but the figures folder of its EVAL.md (results about the checkpoint: a new figures file changes no fingerprint)."""
    files = [ckpt / name for name in ("config.json", "dataset_statistics.json", "example_batch.msgpack", "harness.toml")
             if (ckpt / name).is_file()]
    for sub in sorted(p for p in ckpt.iterdir() if p.is_dir()):
        if (sub.name.isdigit() and (step is None or int(sub.name) != step)) or sub.name == FIGURES_FOLDER:
            continue
        files += [p for p in sub.rglob("*") if p.is_file()]
    return files


def tokenizer_identity(source: str, text_tokenizer: str | None = None) -> dict | None:
    """The identity (kind, name, vocab_size, max_length, sha256, path) of the text tokenizer a model source is run
    with (None: a goal-conditioned model), resolved as loading resolves it, without reading parameters."""
    from harness.octo.loading import resolve_text_tokenizer

    tokenizer = resolve_text_tokenizer(source, text_tokenizer)
    return None if tokenizer is None else tokenizer.identity()


def _tokenizer_line(identity: dict) -> str:
    return f"tokenizer {identity['kind']} {identity['vocab_size']} {identity['max_length']} {identity['sha256']}\n"


def model_fingerprint(source: str, text_tokenizer: str | None = None) -> tuple[str, dict]:
    """(fingerprint, details) of a model source, from its files (stream-hashed; a hub model from the local cache).

    random:<preset> -> "preset:<name>+<tokenizer kind>:<sha256 or vocabulary size>" (weights are drawn from a
    fixed seed); random:<path> and checkpoint folders -> "sha256:<hex>" over (relative path, size, sha256) of
    `checkpoint_files` and, when the tokenizer is not one of those files (t5-base from the Hugging Face cache,
    the fallback, a --text-tokenizer file), a line with its kind, vocabulary size and sha256: a changed tokenizer
    changes the fingerprint. details["tokenizer"] holds the identity.
    """
    from harness.octo import checkpoint, presets

    tokenizer = tokenizer_identity(source, text_tokenizer)
    if source.startswith("random:"):
        spec = source[len("random:"):]
        if spec in presets.preset_names():
            fp = f"preset:{spec}"
            if tokenizer is not None:
                fp += f"+{tokenizer['kind']}:{(tokenizer['sha256'] or str(tokenizer['vocab_size']))[:16]}"
            return fp, {"kind": "preset", "preset": spec, "tokenizer": tokenizer}
        path = Path(spec).expanduser()
        root = path if path.is_dir() else path.parent
        files = checkpoint_files(root, None) if path.is_dir() else [path]
        files = [f for f in files if not f.relative_to(root).parts[0].isdigit()]  # random weights: no params read
    else:
        root = checkpoint.resolve_checkpoint_dir(source)
        step = checkpoint.select_step(root, None)
        files = checkpoint_files(root, step)
    if not files:
        raise FileNotFoundError(f"{source}: no checkpoint files to fingerprint")
    fp, entries = files_fingerprint(root, files)
    hashed = {p.resolve() for p in files}
    if tokenizer is not None and (tokenizer["path"] is None or Path(tokenizer["path"]).resolve() not in hashed):
        lines = "".join(f"{name} {e['size']} {e['sha256']}\n" for name, e in entries.items()) + _tokenizer_line(tokenizer)
        fp = "sha256:" + hashlib.sha256(lines.encode()).hexdigest()
    return fp, {"kind": "files", "root": str(root), "files": entries, "tokenizer": tokenizer}

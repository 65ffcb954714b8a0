"""Building an `OctoModel`: from a checkpoint folder, from the Hugging Face hub, or with random weights.

    load_pretrained("/path/to/checkpoint")              # Octo save_pretrained folder, latest step
    load_pretrained("hf://rail-berkeley/octo-base-1.5")  # via the HF cache (HF_HUB_OFFLINE honoured)
    load_pretrained("random:octo-small-1.5")             # released architecture, random weights, no download

Loading builds the expected parameter tree abstractly (jax.eval_shape, no compute; `expected_params`), reads the
checkpoint, checks every path and shape against it, and only then moves arrays to the device.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from pathlib import Path
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from harness.octo import checkpoint, presets
from harness.octo.config import LowdimTokenizerConfig, OctoConfig, parameter_estimate
from harness.octo.errors import ConfigError, HubUnavailableError
from harness.octo.model import OctoModel, example_lowdim_sizes, example_observation_sizes
from harness.octo.network import init_params, random_params

log = logging.getLogger(__name__)

RANDOM_PREFIX = "random:"
RANDOM_SEED = 0  # random models draw their weights from this seed (network.random_params)


def load_pretrained(uri: str, step: int | None = None, *, text_tokenizer: str | None = None,
                    cache_dir: str | Path | None = None) -> OctoModel:
    """Load an Octo model.

    uri: a local checkpoint folder, "hf://owner/name" (Hugging Face cache; honours HF_HUB_OFFLINE),
    "random:octo-small-1.5" / "random:octo-base-1.5", or "random:<config.json or checkpoint folder>"
    (that architecture with deterministic random weights, seed RANDOM_SEED).
    step: parameter step to load (default: the latest). text_tokenizer: override the tokenizer named by
    the config (a hub name, a tokenizer.json path, or "fallback"). cache_dir: Hugging Face cache folder.
    """
    if uri.startswith(RANDOM_PREFIX):
        return _random_model(uri, text_tokenizer, cache_dir)
    ckpt = checkpoint.resolve_checkpoint_dir(uri, cache_dir)
    config = OctoConfig.from_json(checkpoint.require_file(ckpt, "config.json"))
    check_memory(config, uri)
    example = checkpoint.read_example_batch(ckpt)
    statistics = checkpoint.read_dataset_statistics(ckpt)
    step = checkpoint.select_step(ckpt, step)
    t5 = _t5_config(config, ckpt)
    shapes = _input_shapes(config, example)
    start = time.perf_counter()
    raw = checkpoint.read_params(ckpt, step)
    checkpoint.check_layer_count(raw, config.transformer.num_layers, ckpt / "config.json")  # before tracing N blocks
    expected = expected_params(config, t5, shapes)
    checkpoint.check_param_tree(expected, raw)
    params = jax.tree.map(lambda e, r: jnp.asarray(r, dtype=e.dtype), expected, raw)
    del raw
    log.info("loaded %s step %d (%d parameters) in %.1f s", uri, step,
             sum(int(np.prod(x.shape)) for x in jax.tree.leaves(params)), time.perf_counter() - start)
    return OctoModel(config=config, params=params, example_batch=example, dataset_statistics=statistics,
                     text_tokenizer=_text_tokenizer(config, text_tokenizer, t5, False, cache_dir, ckpt), t5_config=t5,
                     source=uri, is_random=False, checkpoint_dir=ckpt)


def expected_params(config: OctoConfig, t5, shapes: Mapping) -> dict:
    """The parameter tree `network.init_params` makes for this config and these input shapes, as ShapeDtypeStructs
    (jax.eval_shape: nothing computed), traced with one transformer block and at most two T5 blocks: the blocks
    after those are made alike (the same module with the same arguments), so their trees are copies of the last
    traced one. The same tree as tracing every block (tests/octo/test_expected_params.py), for a fraction of the
    tracing (octo-small's 12 + 12 blocks: about 5 s of its 6 on one core)."""
    layers = config.transformer.num_layers
    t5_layers = t5.num_layers if t5 is not None else 0
    traced = dataclasses.replace(config, transformer=dataclasses.replace(config.transformer, num_layers=min(layers, 1)))
    traced_t5 = dataclasses.replace(t5, num_layers=min(t5_layers, 2)) if t5 is not None else None
    tree = jax.eval_shape(lambda key: init_params(key, traced, t5_config=traced_t5, **shapes), jax.random.PRNGKey(0))
    if layers > 1:
        blocks = tree["octo_transformer"]["BlockTransformer_0"]["Transformer_0"]
        blocks.update({f"encoderblock_{i}": blocks["encoderblock_0"] for i in range(1, layers)})
    if t5_layers > 2:
        blocks = tree["octo_transformer"][f"task_tokenizers_{config.language.name}"]["hf_model"]["encoder"]["block"]
        blocks.update({str(i): blocks["1"] for i in range(2, t5_layers)})
    return jax.tree.map(lambda leaf: leaf, tree)  # dicts in jax's (sorted) key order, as eval_shape returns them


def available_memory() -> int | None:
    """Bytes of memory this machine can still give (MemAvailable of /proc/meminfo; None where unknown)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(config: OctoConfig, uri: str, available: int | None = None) -> None:
    """Refuse, before any array is made, a config whose parameters alone (float32, a lower bound from its numbers)
    would not fit in the memory this machine has available: one line naming the numbers and the fix."""
    available = available_memory() if available is None else available
    need = 4 * parameter_estimate(config)
    if available is not None and need > available:
        t = config.transformer
        raise ConfigError(f"{uri}: its config.json describes at least {need / 2**30:.1f} GiB of parameters "
                          f"({t.num_layers} layers, mlp_dim {t.mlp_dim}, token_embedding_size "
                          f"{config.token_embedding_size}) but this machine has {available / 2**30:.1f} GiB available; "
                          "check the checkpoint's config.json, or load it on a machine with more memory")


def _random_config(uri: str) -> tuple[OctoConfig, Path | None]:
    """(config, folder it came from or None for a preset) of a random:<preset | config.json | folder> source."""
    spec = uri[len(RANDOM_PREFIX):]
    if spec in presets.preset_names():
        return OctoConfig.from_dict(presets.preset_config(spec)), None
    path = Path(spec).expanduser()
    if path.is_dir():
        return OctoConfig.from_json(checkpoint.require_file(path, "config.json")), path
    if path.is_file():
        return OctoConfig.from_json(path), path.parent
    raise checkpoint.CheckpointNotFoundError(
        f"{uri}: no such preset or path; use random:{' | random:'.join(presets.preset_names())} "
        "or random:<config.json or checkpoint folder>"
    )


def resolve_text_tokenizer(uri: str, text_tokenizer: str | None = None, *, cache_dir: str | Path | None = None):
    """The TextTokenizer `load_pretrained(uri, text_tokenizer=...)` uses, found without reading any parameters
    (None for a goal-conditioned model); what the run's model fingerprint identifies the tokenizer by."""
    if uri.startswith(RANDOM_PREFIX):
        config, ckpt = _random_config(uri)
        return _text_tokenizer(config, text_tokenizer, _t5_config(config, ckpt), True, cache_dir, warn=False)
    ckpt = checkpoint.resolve_checkpoint_dir(uri, cache_dir)
    config = OctoConfig.from_json(checkpoint.require_file(ckpt, "config.json"))
    return _text_tokenizer(config, text_tokenizer, _t5_config(config, ckpt), False, cache_dir, ckpt, warn=False)


def _random_model(uri: str, text_tokenizer: str | None, cache_dir) -> OctoModel:
    statistics: dict = {}
    config, ckpt = _random_config(uri)
    check_memory(config, uri)
    if ckpt is None:
        example = _synthetic_example_batch(config, presets.IMAGE_SIZES, presets.WINDOW_SIZE)
    else:
        if (ckpt / "example_batch.msgpack").is_file():
            example = checkpoint.read_example_batch(ckpt)
        else:
            example = _synthetic_example_batch(config, _default_image_sizes(config), config.window_size)
        if (ckpt / "dataset_statistics.json").is_file():
            statistics = checkpoint.read_dataset_statistics(ckpt)
    t5 = _t5_config(config, ckpt)
    shapes = _input_shapes(config, example)
    expected = expected_params(config, t5, shapes)
    params = random_params(expected, RANDOM_SEED)
    log.warning("RANDOM MODEL %s: weights are randomly initialised (seed %d); its actions and attention are meaningless",
                uri, RANDOM_SEED)
    return OctoModel(config=config, params=params, example_batch=example, dataset_statistics=statistics,
                     text_tokenizer=_text_tokenizer(config, text_tokenizer, t5, True, cache_dir), t5_config=t5,
                     source=uri, is_random=True, checkpoint_dir=ckpt)


def _t5_config(config: OctoConfig, ckpt: Path | None):
    if config.language is None:
        return None
    from harness.octo.t5 import t5_config_for

    try:
        return t5_config_for(config.language.encoder, ckpt)
    except (ValueError, FileNotFoundError) as e:
        raise ConfigError(f"language encoder {config.language.encoder!r}: {e}") from None


def _text_tokenizer(config: OctoConfig, override: str | None, t5, allow_fallback: bool, cache_dir,
                    ckpt: Path | None = None, warn: bool = True):
    """override: None or "auto" (the config's text processor), "fallback", a hub name or a tokenizer.json path."""
    if config.language is None:
        return None
    from harness.octo.text import fallback_tokenizer, load_text_tokenizer

    max_length = _language_tokens(config)
    override = None if override == "auto" else override
    name = override or (config.text_processor.tokenizer_name if config.text_processor else None)
    if name is None or name == "fallback":
        if warn:
                log.warning("using the deterministic fallback text tokenizer (NOT T5) over %d ids%s", t5.vocab_size,
                        "" if name else " because config.json has no text_processor")
        return fallback_tokenizer(t5.vocab_size, max_length)
    if ckpt is not None and not override and not Path(name).is_absolute() and ".." not in Path(name).parts \
            and (ckpt / name / "tokenizer.json").is_file():
        name = str(ckpt / name)  # a tokenizer folder inside the checkpoint, as the T5 config folder can be
    try:
        # a random model falls back rather than wait on the hub: its weights make any tokenizer arbitrary anyway
        return load_text_tokenizer(name, max_length, allow_fallback=allow_fallback, vocab_size=t5.vocab_size,
                                   cache_dir=cache_dir, cache_only=allow_fallback, warn=warn)
    except FileNotFoundError as e:
        raise HubUnavailableError(f"{e} (or --text-tokenizer PATH to a tokenizer.json, or --text-tokenizer fallback "
                                  "to run without it; text_tokenizer= in Python)") from None


def _input_shapes(config: OctoConfig, example: dict) -> dict:
    """Image sizes, low-dim sizes, window and language length that fix the parameter shapes."""
    obs = example["observation"]
    images, window = example_observation_sizes(obs, config.window_size)
    lowdim = example_lowdim_sizes(config, obs)
    language = example.get("task", {}).get("language_instruction")
    n_lang = int(np.shape(language["input_ids"])[1]) if isinstance(language, Mapping) else _language_tokens(config)
    return {"image_sizes": images, "window": window, "lowdim_sizes": lowdim, "language_tokens": n_lang}


def _language_tokens(config: OctoConfig) -> int:
    """Instruction length in tokens: the config's text processor's, else the released models' default."""
    return config.text_processor.max_length if config.text_processor else presets.LANGUAGE_TOKENS


def _default_image_sizes(config: OctoConfig) -> dict[str, tuple[int, int]]:
    sizes = {}
    for tok in config.observation_tokenizers:
        if isinstance(tok, LowdimTokenizerConfig):
            raise ConfigError("random init of a config with a LowdimObsTokenizer needs example_batch.msgpack next to config.json")
        for key in tok.obs_stack_keys:
            if not key.isidentifier():
                raise ConfigError(f"cannot infer an image key from pattern {key!r}; put example_batch.msgpack next to config.json")
            side = presets.IMAGE_SIZES.get(key, (256, 256))
            sizes[key] = side
    log.info("no example_batch.msgpack: assuming image sizes %s", sizes)
    return sizes


def _synthetic_example_batch(config: OctoConfig, image_sizes: Mapping[str, tuple[int, int]], window: int) -> dict:
    obs = {k: np.zeros((1, window, h, w, 3), np.uint8) for k, (h, w) in image_sizes.items()}
    obs["timestep_pad_mask"] = np.ones((1, window), bool)
    task: dict[str, Any] = {k: np.zeros((1, h, w, 3), np.uint8) for k, (h, w) in image_sizes.items()}
    task["pad_mask_dict"] = {k: np.zeros((1,), bool) for k in image_sizes}
    if config.language is not None:
        n = _language_tokens(config)
        task["language_instruction"] = {"input_ids": np.zeros((1, n), np.int32), "attention_mask": np.zeros((1, n), np.int32)}
        task["pad_mask_dict"]["language_instruction"] = np.ones((1,), bool)
    return {"observation": obs, "task": task}

"""Octo's config.json, parsed once into frozen dataclasses.

Octo names its parts with ModuleSpecs (`{"module": ..., "name": ..., "args": [], "kwargs": {...}}`).
`OctoConfig.from_dict` turns the whole `config.json` into the dataclasses below, filling in the
defaults of the original modules (octo-models/octo @ 241fb35), applying the shims Octo applies to
older configs (1.0 models: `pred_horizon`, no `use_correct_attention`, no `repeat_task_tokens`),
and rejecting anything this runtime does not implement with an `UnsupportedModuleError` that names
the module or option and lists what is supported.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Union

from harness.bounded import BoundsError, read_json
from harness.octo.errors import ConfigError, OctoError, UnsupportedModuleError

_TOKENIZERS = "octo.model.components.tokenizers"
_ENCODERS = "octo.model.components.vit_encoders"
_HEADS = "octo.model.components.action_heads"

SUPPORTED_MODULES = (
    f"{_TOKENIZERS}:ImageTokenizer",
    f"{_TOKENIZERS}:LanguageTokenizer",
    f"{_TOKENIZERS}:LowdimObsTokenizer",
    f"{_ENCODERS}:SmallStem",
    f"{_ENCODERS}:SmallStem16",
    f"{_ENCODERS}:SmallStem32",
    f"{_ENCODERS}:PatchEncoder",
    f"{_HEADS}:DiffusionActionHead",
    f"{_HEADS}:L1ActionHead",
    f"{_HEADS}:MSEActionHead",
    f"{_HEADS}:ContinuousActionHead",
)


# ----------------------------------------------------------------------------- image stems


@dataclass(frozen=True)
class StemConfig:
    """SmallStem* (strided StdConv+GroupNorm+ReLU layers, then a patchifying conv) or PatchEncoder."""

    module_name: str  # Octo class name, e.g. "SmallStem16"; the parameter scope is f"{module_name}_0"
    patch_size: int
    num_features: int
    img_norm_type: str = "default"  # "default": x/127.5-1; "imagenet": (x/255-mean)/std
    kernel_sizes: tuple[int, ...] = ()  # empty for PatchEncoder
    strides: tuple[int, ...] = ()
    features: tuple[int, ...] = ()
    padding: tuple[int, ...] = ()

    @property
    def is_patch_encoder(self) -> bool:
        return self.module_name == "PatchEncoder"

    @property
    def downsample(self) -> int:
        """Total spatial reduction from image pixels to tokens."""
        if self.is_patch_encoder:
            return self.patch_size
        factor = 1
        for s in self.strides:
            factor *= s
        return factor * max(self.patch_size // 16, 1)

    def grid(self, height: int, width: int) -> tuple[int, int]:
        """(rows, cols) of the token grid for an input image of (height, width)."""
        if self.is_patch_encoder:
            return height // self.patch_size, width // self.patch_size
        h, w = height, width
        for k, s, p in zip(self.kernel_sizes, self.strides, self.padding):
            h = (h + 2 * p - k) // s + 1
            w = (w + 2 * p - k) // s + 1
        e = max(self.patch_size // 16, 1)
        return h // e, w // e


# ----------------------------------------------------------------------------- tokenizers


@dataclass(frozen=True)
class ImageTokenizerConfig:
    name: str  # tokenizer name in config.json, e.g. "primary" -> group "obs_primary"
    encoder: StemConfig
    obs_stack_keys: tuple[str, ...]  # regexes (re.match) over observation keys, stacked channel-wise
    task_stack_keys: tuple[str, ...]  # regexes over task keys (goal images), stacked after the observations
    proper_pad_mask: bool = True


@dataclass(frozen=True)
class LowdimTokenizerConfig:
    name: str  # e.g. "proprio" -> group "obs_proprio"
    obs_keys: tuple[str, ...]
    discretize: bool = False
    n_bins: int = 256
    bin_type: str = "uniform"
    low: float = 0.0
    high: float = 1.0
    proper_pad_mask: bool = True


@dataclass(frozen=True)
class LanguageTokenizerConfig:
    name: str  # e.g. "language" -> group "task_language"
    encoder: str  # HF name ("t5-base") or a folder inside the checkpoint ("t5-tiny")
    proper_pad_mask: bool = True


ObservationTokenizerConfig = Union[ImageTokenizerConfig, LowdimTokenizerConfig]


# ----------------------------------------------------------------------------- transformer and heads


@dataclass(frozen=True)
class TransformerConfig:
    num_layers: int
    mlp_dim: int
    num_heads: int


@dataclass(frozen=True)
class MapHeadConfig:
    """Multi-head attention pooling (MAPHead defaults in Octo)."""

    num_heads: int = 8
    num_readouts: int = 1
    mlp_dim: int | None = None  # None: 4 * token_embedding_size


@dataclass(frozen=True)
class DiffusionHeadConfig:
    readout_key: str
    action_horizon: int
    action_dim: int
    use_map: bool = False
    max_action: float = 5.0
    time_dim: int = 32
    num_blocks: int = 3
    hidden_dim: int = 256
    use_layer_norm: bool = True
    diffusion_steps: int = 20
    map_head: MapHeadConfig = field(default_factory=MapHeadConfig)


@dataclass(frozen=True)
class ContinuousHeadConfig:
    readout_key: str
    action_horizon: int
    action_dim: int
    use_map: bool = True
    max_action: float = 5.0
    map_head: MapHeadConfig = field(default_factory=MapHeadConfig)


HeadConfig = Union[DiffusionHeadConfig, ContinuousHeadConfig]


@dataclass(frozen=True)
class TextProcessorConfig:
    tokenizer_name: str  # e.g. "t5-base"
    max_length: int = 16


@dataclass(frozen=True)
class OctoConfig:
    observation_tokenizers: tuple[ObservationTokenizerConfig, ...]  # config.json order = sequence order
    task_tokenizers: tuple[LanguageTokenizerConfig, ...]
    readouts: tuple[tuple[str, int], ...]  # (name, tokens) in config order
    heads: tuple[tuple[str, HeadConfig], ...]
    token_embedding_size: int
    transformer: TransformerConfig
    max_horizon: int
    repeat_task_tokens: bool
    use_correct_attention: bool
    window_size: int
    text_processor: TextProcessorConfig | None
    checkpoint_format: str = "1.5"  # "1.0" for December 2023 configs (pred_horizon, no use_correct_attention)

    @property
    def language(self) -> LanguageTokenizerConfig | None:
        return self.task_tokenizers[0] if self.task_tokenizers else None

    @property
    def action_head(self) -> HeadConfig:
        for name, head in self.heads:
            if name == "action":
                return head
        raise UnsupportedModuleError(f"config has no 'action' head (heads: {[n for n, _ in self.heads]}); Octo needs one")

    @classmethod
    def from_json(cls, path: str | Path) -> "OctoConfig":
        path = Path(path)
        try:
            data = read_json(path)
        except BoundsError as e:
            raise ConfigError(f"{e}; restore the checkpoint's config.json") from None
        except json.JSONDecodeError as e:
            raise ConfigError(f"{path} is not valid JSON ({e}); restore the checkpoint's config.json") from None
        return cls.from_dict(data)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "OctoConfig":
        """A config.json's content -> OctoConfig; a value of the wrong type or range is a ConfigError (one line)."""
        try:
            return cls._from_dict(data)
        except OctoError:  # already one line naming the field (ConfigError, UnsupportedModuleError)
            raise
        except (TypeError, ValueError, AttributeError, KeyError) as e:
            detail = f"missing {e}" if isinstance(e, KeyError) else str(e).splitlines()[0]
            raise ConfigError(f"config.json holds a value Octo cannot use ({type(e).__name__}: {detail}); restore "
                              "the checkpoint's config.json") from None

    @classmethod
    def _from_dict(cls, data: Mapping[str, Any]) -> "OctoConfig":
        if "model" not in data:
            raise ConfigError("config.json has no 'model' entry; is this an Octo checkpoint's config.json?")
        m = data["model"]
        for key in ("observation_tokenizers", "heads", "readouts", "token_embedding_size", "transformer_kwargs"):
            if key not in m:
                raise ConfigError(f"config.json model is missing {key!r}; is this an Octo checkpoint's config.json?")
        tk = dict(m["transformer_kwargs"])
        if tk.get("add_position_embedding", False):
            raise UnsupportedModuleError("transformer_kwargs.add_position_embedding=True is not supported (Octo asserts it is False)")
        heads_count = tk.get("num_attention_heads", tk.get("num_heads"))
        if heads_count is None:
            raise ConfigError("transformer_kwargs has no num_attention_heads")
        return cls(
            observation_tokenizers=tuple(
                _observation_tokenizer(name, spec) for name, spec in m["observation_tokenizers"].items()
            ),
            task_tokenizers=tuple(_task_tokenizer(name, spec) for name, spec in (m.get("task_tokenizers") or {}).items()),
            readouts=tuple((str(k), int(v)) for k, v in m["readouts"].items()),
            heads=tuple((name, _head(name, spec)) for name, spec in m["heads"].items()),
            token_embedding_size=_count(m["token_embedding_size"], "model.token_embedding_size"),
            transformer=TransformerConfig(
                num_layers=_count(tk["num_layers"], "model.transformer_kwargs.num_layers"),
                mlp_dim=_count(tk["mlp_dim"], "model.transformer_kwargs.mlp_dim"),
                num_heads=_count(heads_count, "model.transformer_kwargs.num_attention_heads"),
            ),
            max_horizon=int(m.get("max_horizon", 10)),
            repeat_task_tokens=bool(m.get("repeat_task_tokens", False)),
            use_correct_attention=bool(m.get("use_correct_attention", False)),
            window_size=_count(data.get("window_size", 2), "window_size"),
            text_processor=_text_processor(data.get("text_processor")),
            checkpoint_format="1.0" if _is_octo_1_0(m) else "1.5",
        )


def _count(value: Any, name: str) -> int:
    """A positive whole number from config.json (an integral float such as 2048.0 too), or a ConfigError naming it."""
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"config.json {name} must be a positive whole number, got {value!r}; restore the "
                          "checkpoint's config.json")
    return value


def parameter_estimate(config: "OctoConfig") -> int:
    """A lower bound on the parameters of the transformer `config` describes (attention, MLP and layer norms of its
    blocks), computed from the numbers alone so it can be checked before any array is made."""
    d, layers, mlp = config.token_embedding_size, config.transformer.num_layers, config.transformer.mlp_dim
    per_block = 4 * d * d + 4 * d + 2 * d * mlp + mlp + d + 4 * d
    return layers * per_block


def _is_octo_1_0(model: Mapping[str, Any]) -> bool:
    """A December 2023 (Octo 1.0) model config: heads name their horizon pred_horizon."""
    heads = model.get("heads") or {}
    return any(isinstance(h, Mapping) and "pred_horizon" in (h.get("kwargs") or {}) for h in heads.values())


# ----------------------------------------------------------------------------- ModuleSpec parsing


def _spec(spec: Any, where: str) -> tuple[str, str, dict]:
    """(module, class name, kwargs) of a ModuleSpec dict or a 'module:Name' string."""
    if isinstance(spec, str) and ":" in spec:
        module, name = spec.split(":", 1)
        return module, name, {}
    if not isinstance(spec, Mapping) or "name" not in spec:
        raise ConfigError(f"{where}: expected a ModuleSpec {{module, name, args, kwargs}}, got {spec!r}")
    if spec.get("args"):
        raise UnsupportedModuleError(f"{where}: positional ModuleSpec args {spec['args']!r} are not supported; use kwargs")
    return str(spec.get("module", "")), str(spec["name"]), dict(spec.get("kwargs") or {})


def _require(module: str, name: str, allowed: tuple[str, ...], where: str) -> None:
    full = f"{module}:{name}"
    if full not in allowed:
        raise UnsupportedModuleError(
            f"{where}: unsupported module {full}; supported: {', '.join(a.split(':')[1] for a in allowed)}"
        )


def _check_kwargs(kwargs: dict, known: dict, where: str) -> dict:
    """Known kwargs merged over defaults; unknown ones and unsupported values raise."""
    unknown = sorted(set(kwargs) - set(known))
    if unknown:
        raise UnsupportedModuleError(f"{where}: unsupported option(s) {unknown}; supported: {sorted(known)}")
    return {**known, **kwargs}


def _unsupported_if(condition: bool, where: str, what: str) -> None:
    if condition:
        raise UnsupportedModuleError(f"{where}: {what} is not supported by this runtime")


def _stem(spec: Any, where: str) -> StemConfig:
    module, name, kw = _spec(spec, where)
    _require(module, name, tuple(s for s in SUPPORTED_MODULES if s.startswith(_ENCODERS)), where)
    if name == "PatchEncoder":
        kw = _check_kwargs(kw, {"use_film": False, "patch_size": 32, "num_features": 512, "img_norm_type": "default"}, where)
        _unsupported_if(kw["use_film"], where, "use_film=True (FiLM conditioning)")
        return StemConfig(module_name=name, patch_size=int(kw["patch_size"]), num_features=int(kw["num_features"]),
                          img_norm_type=str(kw["img_norm_type"]))
    defaults = {
        "use_film": False,
        "patch_size": {"SmallStem": 32, "SmallStem16": 16, "SmallStem32": 32}[name],
        "kernel_sizes": (3, 3, 3, 3),
        "strides": (2, 2, 2, 2),
        "features": (32, 96, 192, 384),
        "padding": (1, 1, 1, 1),
        "num_features": 512,
        "img_norm_type": "default",
    }
    kw = _check_kwargs(kw, defaults, where)
    _unsupported_if(kw["use_film"], where, "use_film=True (FiLM conditioning)")
    _unsupported_if(kw["img_norm_type"] not in ("default", "imagenet"), where, f"img_norm_type={kw['img_norm_type']!r}")
    lengths = {len(kw[k]) for k in ("kernel_sizes", "strides", "features", "padding")}
    if len(lengths) != 1:
        raise ConfigError(f"{where}: kernel_sizes, strides, features and padding must have the same length")
    if any(not isinstance(p, int) for p in kw["padding"]):
        raise UnsupportedModuleError(f"{where}: only integer padding is supported, got {kw['padding']!r}")
    return StemConfig(
        module_name=name,
        patch_size=int(kw["patch_size"]),
        num_features=int(kw["num_features"]),
        img_norm_type=str(kw["img_norm_type"]),
        kernel_sizes=tuple(int(k) for k in kw["kernel_sizes"]),
        strides=tuple(int(s) for s in kw["strides"]),
        features=tuple(int(f) for f in kw["features"]),
        padding=tuple(int(p) for p in kw["padding"]),
    )


def _observation_tokenizer(name: str, spec: Any) -> ObservationTokenizerConfig:
    where = f"observation_tokenizers.{name}"
    module, cls, kw = _spec(spec, where)
    _require(module, cls, (f"{_TOKENIZERS}:ImageTokenizer", f"{_TOKENIZERS}:LowdimObsTokenizer"), where)
    if cls == "ImageTokenizer":
        kw = _check_kwargs(kw, {
            "encoder": None, "use_token_learner": False, "num_tokens": 8, "conditioning_type": "none",
            "obs_stack_keys": ("image_.*", "depth_.*"), "task_stack_keys": (), "task_film_keys": (),
            "proper_pad_mask": True,
        }, where)
        _unsupported_if(kw["use_token_learner"], where, "use_token_learner=True")
        _unsupported_if(kw["conditioning_type"] != "none", where, f"conditioning_type={kw['conditioning_type']!r}")
        _unsupported_if(bool(kw["task_film_keys"]), where, "task_film_keys (FiLM conditioning)")
        if kw["encoder"] is None:
            raise ConfigError(f"{where}: ImageTokenizer has no encoder")
        return ImageTokenizerConfig(
            name=name,
            encoder=_stem(kw["encoder"], f"{where}.encoder"),
            obs_stack_keys=tuple(kw["obs_stack_keys"]),
            task_stack_keys=tuple(kw["task_stack_keys"]),
            proper_pad_mask=bool(kw["proper_pad_mask"]),
        )
    kw = _check_kwargs(kw, {
        "obs_keys": (), "discretize": False, "proper_pad_mask": True, "n_bins": 256, "bin_type": "uniform",
        "low": 0.0, "high": 1.0, "dropout_rate": 0.0,
    }, where)
    if not kw["obs_keys"]:
        raise ConfigError(f"{where}: LowdimObsTokenizer needs obs_keys")
    _unsupported_if(kw["bin_type"] not in ("uniform", "normal"), where, f"bin_type={kw['bin_type']!r}")
    return LowdimTokenizerConfig(
        name=name, obs_keys=tuple(kw["obs_keys"]), discretize=bool(kw["discretize"]), n_bins=int(kw["n_bins"]),
        bin_type=str(kw["bin_type"]), low=float(kw["low"]), high=float(kw["high"]),
        proper_pad_mask=bool(kw["proper_pad_mask"]),
    )


def _task_tokenizer(name: str, spec: Any) -> LanguageTokenizerConfig:
    where = f"task_tokenizers.{name}"
    module, cls, kw = _spec(spec, where)
    _require(module, cls, (f"{_TOKENIZERS}:LanguageTokenizer",), where)
    kw = _check_kwargs(kw, {"encoder": None, "finetune_encoder": False, "proper_pad_mask": True}, where)
    if not kw["encoder"] or "t5" not in str(kw["encoder"]).lower():
        raise UnsupportedModuleError(f"{where}: encoder={kw['encoder']!r} is not supported; only T5 encoders (e.g. 't5-base')")
    return LanguageTokenizerConfig(name=name, encoder=str(kw["encoder"]), proper_pad_mask=bool(kw["proper_pad_mask"]))


def _head(name: str, spec: Any) -> HeadConfig:
    where = f"heads.{name}"
    module, cls, kw = _spec(spec, where)
    _require(module, cls, tuple(s for s in SUPPORTED_MODULES if s.startswith(_HEADS)), where)
    if "pred_horizon" in kw:  # Octo 1.0 configs; Octo's loader renames it to action_horizon
        kw = dict(kw)
        kw["action_horizon"] = kw.pop("pred_horizon")
    if cls == "DiffusionActionHead":
        kw = _check_kwargs(kw, {
            "readout_key": None, "use_map": False, "action_horizon": 1, "action_dim": 7, "max_action": 5.0,
            "loss_type": "mse", "time_dim": 32, "num_blocks": 3, "dropout_rate": 0.0, "hidden_dim": 256,
            "use_layer_norm": True, "diffusion_steps": 20, "n_diffusion_samples": 1,
        }, where)
        if not kw["readout_key"]:
            raise ConfigError(f"{where}: readout_key is required")
        return DiffusionHeadConfig(
            readout_key=str(kw["readout_key"]), action_horizon=int(kw["action_horizon"]),
            action_dim=int(kw["action_dim"]), use_map=bool(kw["use_map"]), max_action=float(kw["max_action"]),
            time_dim=int(kw["time_dim"]), num_blocks=int(kw["num_blocks"]), hidden_dim=int(kw["hidden_dim"]),
            use_layer_norm=bool(kw["use_layer_norm"]), diffusion_steps=int(kw["diffusion_steps"]),
        )
    kw = _check_kwargs(kw, {
        "readout_key": None, "use_map": cls != "ContinuousActionHead", "action_horizon": 1, "action_dim": 7,
        "max_action": 5.0, "loss_type": "l1" if cls == "L1ActionHead" else "mse",
    }, where)
    if not kw["readout_key"]:
        raise ConfigError(f"{where}: readout_key is required")
    return ContinuousHeadConfig(
        readout_key=str(kw["readout_key"]), action_horizon=int(kw["action_horizon"]),
        action_dim=int(kw["action_dim"]), use_map=bool(kw["use_map"]), max_action=float(kw["max_action"]),
    )


def _text_processor(spec: Any) -> TextProcessorConfig | None:
    if spec is None:
        return None
    module, name, kw = _spec(spec, "text_processor")
    if name != "HFTokenizer":
        raise UnsupportedModuleError(f"text_processor: unsupported module {module}:{name}; supported: HFTokenizer")
    if kw.get("encode_with_model", False):
        raise UnsupportedModuleError("text_processor: encode_with_model=True is not supported")
    tk = dict(kw.get("tokenizer_kwargs") or {})
    return TextProcessorConfig(tokenizer_name=str(kw.get("tokenizer_name", "t5-base")), max_length=int(tk.get("max_length", 16)))

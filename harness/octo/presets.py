"""Built-in architectures for random initialisation: `random:octo-small-1.5`, `random:octo-base-1.5`.

The values are those of the released octo-{small,base}-1.5 config.json (octo-models/octo
`scripts/configs/octo_pretrain_config.py`, vit_s / vit_b), embedded here so a random model needs no
download and no files outside the package. Both see 256x256 primary and 128x128 wrist images with a
window of 2 and 16 language tokens from t5-base.
"""

from __future__ import annotations

_SIZES = {  # token_embedding_size, attention heads, mlp_dim (12 layers each)
    "octo-small-1.5": (384, 6, 1536),
    "octo-base-1.5": (768, 12, 3072),
}

IMAGE_SIZES = {"image_primary": (256, 256), "image_wrist": (128, 128)}
WINDOW_SIZE = 2
LANGUAGE_TOKENS = 16


def _spec(module: str, name: str, **kwargs) -> dict:
    return {"module": module, "name": name, "args": [], "kwargs": kwargs}


def _image_tokenizer(key: str) -> dict:
    stem = _spec("octo.model.components.vit_encoders", "SmallStem16")
    return _spec("octo.model.components.tokenizers", "ImageTokenizer",
                 obs_stack_keys=[key], task_stack_keys=[key], encoder=stem)


def preset_names() -> tuple[str, ...]:
    return tuple(_SIZES)


def preset_config(name: str) -> dict:
    """config.json contents of a released architecture (raises KeyError for unknown names)."""
    width, heads, mlp = _SIZES[name]
    return {
        "model": {
            "observation_tokenizers": {
                "primary": _image_tokenizer("image_primary"),
                "wrist": _image_tokenizer("image_wrist"),
            },
            "task_tokenizers": {
                "language": _spec("octo.model.components.tokenizers", "LanguageTokenizer",
                                  encoder="t5-base", finetune_encoder=False),
            },
            "heads": {
                "action": _spec("octo.model.components.action_heads", "DiffusionActionHead",
                                readout_key="readout_action", use_map=False, action_horizon=4, action_dim=7,
                                n_diffusion_samples=1, dropout_rate=0.0),
            },
            "readouts": {"action": 1},
            "token_embedding_size": width,
            "transformer_kwargs": {
                "num_layers": 12, "mlp_dim": mlp, "num_attention_heads": heads, "dropout_rate": 0.0,
                "attention_dropout_rate": 0.0, "add_position_embedding": False,
            },
            "max_horizon": 10,
            "repeat_task_tokens": True,
            "use_correct_attention": True,
        },
        "text_processor": _spec("octo.data.utils.text_processing", "HFTokenizer", tokenizer_name="t5-base",
                                encode_with_model=False,
                                tokenizer_kwargs={"max_length": LANGUAGE_TOKENS, "padding": "max_length",
                                                  "truncation": True, "return_tensors": "np"}),
        "window_size": WINDOW_SIZE,
    }

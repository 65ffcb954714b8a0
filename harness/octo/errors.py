"""User-facing errors of the Octo runtime: one line each, naming the fix.

Every error derives from `OctoError` and, where natural, from the builtin a caller would expect
(`FileNotFoundError` for missing files, `ValueError` for bad contents or inputs), so callers can catch
either.
"""

from __future__ import annotations


class OctoError(Exception):
    """Base class of every error the Octo runtime raises for users."""


class CheckpointNotFoundError(OctoError, FileNotFoundError):
    """The checkpoint directory or one of its required files does not exist."""


class CorruptCheckpointError(OctoError, ValueError):
    """A checkpoint file exists but cannot be decoded (truncated, wrong format)."""


class UnsupportedModuleError(OctoError, ValueError):
    """config.json names an Octo module or option this runtime does not implement."""


class ConfigError(OctoError, ValueError):
    """config.json is malformed (missing keys, wrong types)."""


class ParamTreeMismatchError(OctoError, ValueError):
    """The checkpoint's parameters do not fit the architecture its config describes."""


class UnknownDatasetKeyError(OctoError, ValueError):
    """The requested dataset key is not in the model's dataset statistics."""


class HubUnavailableError(OctoError, FileNotFoundError):
    """An hf:// checkpoint is neither cached nor downloadable (offline mode or no network)."""


class InputError(OctoError, ValueError):
    """Observations or tasks do not have the shapes or dtypes the model expects."""

"""Octo generalist robot policy in JAX/Flax, parameter-compatible with Octo's checkpoints.

`load_pretrained(uri)` gives an `OctoModel` whose `sample_actions` returns actions and the
transformer's attention (`Attention`) from one jitted call. All user-facing errors derive from `OctoError`.
"""

from harness.octo.errors import OctoError
from harness.octo.loading import load_pretrained
from harness.octo.model import Attention, OctoModel

__all__ = ["Attention", "OctoError", "OctoModel", "load_pretrained"]

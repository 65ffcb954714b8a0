"""The policy families the harness can load (one class each, one row in this registry) and the factory over them.

A family says which `--model` sources are its own (`accepts`), how to fingerprint one cheaply before anything loads
(the protocol's `model_fingerprint`), and how to load it into a `Policy`. The built-ins: served policies (`ws://`,
`wss://`: any openpi-protocol policy server) and Octo checkpoints (hf://, random:, a local folder), asked in that
order; other distributions add families under the entry-point group `octo_harness.policies` (envs.plugins).
`load_policy` is the one place a Policy is constructed from a source; `as_policy` wraps an Octo model loaded
elsewhere (a test's or a benchmark's shared fixture).
"""

from __future__ import annotations

from typing import Any

from envs.plugins import PluginRegistry
from harness.policies.base import Policy, PolicyFamily

ENTRY_POINTS = "octo_harness.policies"
BUILTINS = ("harness.policies.served:ServedFamily", "harness.policies.octo:OctoFamily")


class PolicyLoadError(ImportError):
    """A policy family that cannot be loaded (one line naming it)."""


_FAMILIES = PluginRegistry("policy family", PolicyFamily, BUILTINS, ENTRY_POINTS, PolicyLoadError,
                           make=lambda cls: cls())
register = _FAMILIES.register
unregister = _FAMILIES.unregister
registered = _FAMILIES.registered


def family_of(source: str) -> PolicyFamily:
    """The first registered family that accepts `source` (Octo's accepts every other source)."""
    for family in _FAMILIES.values():
        if family.accepts(source):
            return family
    raise ValueError(f"--model {source!r}: no policy family takes it; give a checkpoint folder, hf://, random: or ws://")


def load_policy(source: str, **options: Any) -> Policy:
    """The Policy `--model source` names, loaded by its family (options: text_tokenizer, served conventions, ...)."""
    return family_of(source).load(source, **options)


def policy_fingerprint(source: str, **options: Any) -> tuple[str, dict]:
    return family_of(source).fingerprint(source, **options)


def as_policy(model: Any) -> Policy:
    """A Policy as it is, or an Octo model (harness.octo.OctoModel) loaded elsewhere wrapped as one."""
    if isinstance(model, Policy):
        return model
    from harness.policies.octo import OctoCheckpoint

    return OctoCheckpoint(model)

"""Every policy the harness evaluates, behind one interface: `Policy` (base.py), built by one factory (`load_policy`,
registry.py) from `--model`. Octo checkpoints (octo.py) and policies behind an openpi-protocol websocket server
(served.py) are its implementations; `octo-harness serve` (server.py) serves any of them with that protocol."""

from harness.policies.base import AttentionShape, Capabilities, Policy, PolicyLacksError
from harness.policies.registry import (PolicyFamily, as_policy, family_of, load_policy, policy_fingerprint,
                                       register, registered, unregister)

__all__ = ["AttentionShape", "Capabilities", "Policy", "PolicyFamily", "PolicyLacksError", "as_policy", "family_of",
           "load_policy", "policy_fingerprint", "register", "registered", "unregister"]

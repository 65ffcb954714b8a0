"""Policies behind an openpi-protocol websocket server (`--model ws://HOST:PORT`). Placeholder: being written."""

from __future__ import annotations

from harness.policies.base import PolicyFamily

SERVED_SOURCE = "ws://"  # what the protocol records of any served source: the address is not the policy


class ServedFamily(PolicyFamily):
    name = "served"
    description = "a policy behind an openpi-protocol websocket server (ws://HOST:PORT)"

    def accepts(self, source: str) -> bool:
        return source.startswith(("ws://", "wss://"))

    def protocol_source(self, source: str) -> str:
        return SERVED_SOURCE

    def run_label(self, source: str) -> str:
        return "served"

    def fingerprint(self, source, **options):
        raise NotImplementedError

    def load(self, source, **options):
        raise NotImplementedError

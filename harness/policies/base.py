"""The one interface every policy the harness evaluates implements (`Policy`), and what a policy declares it can do.

A `Policy` is a loaded policy: its conventions (the observations it reads, at what sizes and window, the actions it
returns per inference), what it can do (`Capabilities`) and one batched, stateless inference call
(`inference(config)`: a list of `harness.policy.InferenceRequest` -> one `InferenceResult` each). Everything that
carries an episode from step to step (history window, chunks, rng position) is the harness's `ClosedLoopPolicy`,
the same for every policy, so a policy only answers requests.

The executors, gates and tools use only this interface; `harness.policies.load_policy` (the factory) is the one
place that constructs a policy from `--model`. Implementations: Octo checkpoints (harness/policies/octo.py) and
any policy behind an openpi-protocol websocket server (harness/policies/served.py).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harness.policy import ClosedLoopPolicy
from harness.policy_config import PolicyConfig


class PolicyLacksError(ValueError):
    """A flag asked for something the policy does not declare it can do (message: one line naming the fix)."""


@dataclass(frozen=True)
class Capabilities:
    """What a policy declares it can do, beyond returning action chunks."""

    # readout attention rows and a token map with every inference (PNGs, overlays, attention measures)
    attention: bool = False
    # masks and region replacement inside inference (--intervene, and the probes that change what the policy sees)
    interventions: bool = False
    probes: bool = False  # the per-step probes (harness.probes) run inside its inference
    batched: bool = False  # one call may carry requests of many episodes (the executors batch them)

    def lacking(self) -> list[str]:
        return [name for name, value in self.__dict__.items() if not value and name != "batched"]


@dataclass(frozen=True)
class AttentionShape:
    """The shape of a policy's readout attention (what an estimate of a run's size and a layer flag check need)."""

    layers: int
    heads: int


class Policy(ABC):
    """A loaded policy. Subclasses set the attributes in __init__ and implement `inference`."""

    source: str  # what --model named
    is_random: bool = False  # random weights (a preset drawn from a seed): actions and attention mean nothing
    capabilities: Capabilities = Capabilities()
    window_size: int  # observations per inference (history)
    action_horizon: int  # actions per chunk
    action_dim: int | None  # dims of the actions handed to the env (None: known after the first chunk)
    image_sizes: dict[str, tuple[int, int]]  # camera observation key -> (height, width) it is fed at
    lowdim_sizes: dict[str, int] = {}  # low-dim observation key -> dims
    goal_image_sizes: dict[str, tuple[int, int]] = {}  # goal image key -> (height, width)
    takes_language: bool = True
    dataset_statistics: dict = {}  # {dataset key: statistics} the policy unnormalises with (pre-flight's evidence)
    example_batch: dict | None = None  # a training batch's example (pre-flight's frames), or None
    checkpoint_dir: Path | None = None  # the local folder it was read from (its harness.toml, EVAL.md), or None
    text_tokenizer: Any = None  # the tokenizer object (its label goes into the manifest), or None
    attention_shape: AttentionShape | None = None  # None: the policy gives no attention
    # no action statistics of its own to check (a policy behind a server): the pre-flight action check reads the first
    # chunk it returns instead (harness/run/preflight.py), and a camera without an example frame is inconclusive
    preflight_from_chunk: bool = False

    @abstractmethod
    def inference(self, config: PolicyConfig):
        """The batched, stateless inference for `config`: `__call__(requests) -> results`, `warm_up(request)`,
        `batch_size`, `dataset_key`, `action_dim`, `probes` (the running probes)."""

    def closed_loop(self, config: PolicyConfig, infer=None) -> ClosedLoopPolicy:
        """The per-episode closed-loop policy (`reset`, `step`) over `infer` (default: this policy's inference)."""
        return ClosedLoopPolicy(self, config, infer if infer is not None else self.inference(config))

    def token_map(self, *args, **kwargs):
        """What each attention key is (harness.octo.tokens.TokenMap), or None for a policy without attention."""
        return None

    def identity(self) -> tuple[str, dict] | None:
        """(fingerprint, details) of a policy its family cannot fingerprint from `source` (one built in Python and
        handed to `execute(model=...)`); None: the family fingerprints the source (checkpoint files, a server)."""
        return None

    def describe(self) -> dict:
        """What the manifest records of the policy beyond the protocol (implementation-specific, JSON)."""
        return {}

    @property
    def sample_cache_size(self) -> int:
        """Compiled inference variants (0 where nothing compiles)."""
        return 0

    def close(self) -> None:
        """Release what the policy holds (a connection); idempotent."""

    def require(self, wanted: dict[str, str]) -> None:
        """PolicyLacksError (one line) when a flag in `wanted` ({flag: capability}) asks for what the policy lacks."""
        lacking = [(flag, need) for flag, need in wanted.items() if not getattr(self.capabilities, need)]
        if lacking:
            flags = ", ".join(flag for flag, _ in lacking)
            needs = sorted({need for _, need in lacking})
            raise PolicyLacksError(f"{flags}: {self.source} declares no {' or '.join(needs)} (a policy behind a server "
                                   f"gives actions only); drop {'them' if len(lacking) > 1 else 'it'} for this policy")


class PolicyFamily:
    """One kind of policy source. Subclasses set `name` and implement the three methods."""

    name: str = ""
    description: str = ""

    def accepts(self, source: str) -> bool:
        raise NotImplementedError

    def fingerprint(self, source: str, **options: Any) -> tuple[str, dict]:
        """(fingerprint, details) identifying the policy behind `source`, without loading it where that is costly."""
        raise NotImplementedError

    def load(self, source: str, **options: Any) -> Policy:
        raise NotImplementedError

    # whether a run may map its observations to this family's policies with --served-conventions (a server's keys)
    takes_served_conventions: bool = False

    def declared_conventions(self, source: str) -> dict | None:
        """The harness.toml-format conventions the policy behind `source` declares itself ({} when it declares none),
        or None: read them from its checkpoint folder's harness.toml (harness.run.settings)."""
        return None

    def protocol_source(self, source: str) -> str:
        """What the protocol (and its hash) records of `source`: the source itself, unless where it is reached does
        not define the policy (a server's address: its fingerprint does)."""
        return source

    def run_label(self, source: str) -> str:
        """The short name a run's default folder name starts with (stable while the policy is)."""
        source = source.rstrip("/")
        return source.replace("hf://", "").replace("random:", "random-").split("/")[-1].replace(":", "-") or "model"

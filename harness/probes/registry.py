"""The probe registry: the `Probe` contract, the registered probes in order, and how a stage reaches a probe's parts.

A probe is one `Probe` subclass in one module (or folder) and one registry entry. It declares:
  name            the key of its results in the one mapping `probes` of InferenceResult, PolicyStep and StepRecord
  option          the option field that turns it on (None: on whenever it is registered)
  options         a frozen dataclass of its own option fields (`harness.options.option`: flag, default, help, protocol
                  file types), with `check(config)` validating them; `harness.policy.PolicyConfig` is assembled from
                  the policy's own fields and every registered probe's options, so the flags, the protocol file's keys
                  and the docs' option tables come from the probe's folder
  changes_actions whether turning it on can change the executed actions (False for every built-in probe: they
                  measure beside the actions). `compare` and `regress` let the fields of a probe that never changes
                  actions differ between two runs, and the provenance line counts them as neutral
  every           `every(config)`: it runs at every N-th step the policy infers at (step % N == 0), 0 = never
  run             `run(batch, context) -> payloads`: one payload (or None) per `ProbeItem` of the batch: the requests
                  due at this call with what the call inferred for them
  upright         the payload of a camera shown upright (rollout turns frames upright for the records; default: as is)
  sink            the `harness.outputs.steps.Sink` that writes its files (a class, or "module:Name")
  reader          how its payloads are read back from an episode folder (an object or module with
                  `by_step(directory)` -> {step: payload}; "module" or "module:Name")
  section         its report section (an object with the report's `summarise`, `tables`, `section`, or "module:Name")
  layer           its viewer layer in the Rerun recording (an object with `camera_views(cam, payload)`,
                  `camera_note(payload)`, `plots(payload)`, `header(payload)` and `log(recording, record, payload)`,
                  or "module:Name")
The higher-stage parts (sink, reader, section, layer) are named, not imported, here: the stage that uses a part looks it
up by probe through `part(probe, what)`, so the policy can call probes and the report and viewer can show them while
no import runs back up the stages. A module name starting with "." is relative to the probe's own package
(`cls.__module__`), e.g. ".sink:RelianceLines".

Where probes come from, in this order (the order probes run in at a step, their files are written in and their report
sections and viewer layers appear in):
  1. the built-in probes, named here as "module:Class" (`BUILTINS`) and imported on first use, so this module imports
     none of them and they import it (one direction);
  2. the entry points of the group `octo_harness.probes` of every installed distribution, by name: a probe shipped
     in a package of its own is found by every process that imports the harness, spawned `--workers` and Ray
     workers included;
  3. `register(cls)` / `registered(cls)` at run time: known to this process only, and without options of its own
     (PolicyConfig is assembled before).
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass
from typing import Any, Callable, ClassVar

from envs.plugins import PluginRegistry

PARTS = ("sink", "reader", "section", "layer")
BUILTINS = ("harness.probes.attribution:AttributionProbe", "harness.probes.controls:ControlsProbe",
            "harness.probes.reliance:RelianceProbe", "harness.probes.readout_features:ReadoutFeaturesProbe",
            "harness.probes.action_consistency:ActionConsistencyProbe")
ENTRY_POINTS = "octo_harness.probes"  # the entry-point group a distribution registers its probes under


class ProbeLoadError(ImportError):
    """A probe named by the built-ins or an entry point cannot be loaded (one line naming it)."""


@dataclass(frozen=True, eq=False)
class ProbeItem:
    """One example of a batched inference call as a probe sees it: the request (harness.policy.InferenceRequest: the
    observation window as the policy saw it, task, seed, step, the env's masks when a probe needs them) and what the
    call inferred for it: `chunk` (action_horizon, action_dim) float32, `readout_attention` (layers, heads, readouts,
    keys) float32."""

    request: Any
    chunk: Any
    readout_attention: Any


@dataclass(frozen=True)
class ProbeContext:
    """What the policy's batched inference lends a probe: the model it infers with (the intervened one under
    --intervene), its PolicyConfig, `inputs(requests)` -> (observations, tasks, keys) with the batch axis first,
    `sample(observations, tasks, keys)` -> (actions, attention) of the compiled call, its batch size, and `shared`:
    a dict probes of one inference use to share compiled functions (built once per model)."""

    model: Any
    config: Any
    inputs: Callable
    sample: Callable
    batch_size: int
    shared: dict


class Probe:
    """One per-step probe (see the module docstring). Subclasses set the class attributes and implement `run`;
    an instance is made per batched inference with the ProbeContext (`__init__(context)`)."""

    name: ClassVar[str] = ""
    option: ClassVar[str | None] = None
    options: ClassVar[type | None] = None  # a frozen dataclass of option fields with `check(config)`, or None
    changes_actions: ClassVar[bool] = False  # True: turning it on may change the executed actions
    needs_masks: ClassVar[bool] = False  # the env's masks of the current frame travel with a due request
    masks_error: ClassVar[str] = ""  # one line naming the fix when a due step has no masks
    sink: ClassVar[Any] = None
    reader: ClassVar[Any] = None
    section: ClassVar[Any] = None
    layer: ClassVar[Any] = None

    def __init__(self, context: ProbeContext):
        self.context = context
        self.period = self.every(context.config)

    @classmethod
    def every(cls, config) -> int:
        """Run at every N-th step the policy infers at (step % N == 0); 0 = off. Default: on at every inferred step
        when the option field is set (or when there is none)."""
        return 1 if cls.option is None or getattr(config, cls.option) else 0

    @classmethod
    def in_inference(cls, config) -> bool:
        """Whether it runs inside the policy's inference (True by default). False: its sink computes it from the step
        records alone, so any policy can record it, one that runs no probes too (a policy behind a server); the closed
        loop marks its due inferred steps with an empty payload, as the inference side would (harness.policy)."""
        return True

    @classmethod
    def inference_flag(cls, config) -> str:
        """The flag that asks for its computation in the inference (named when a policy cannot run it)."""
        return f"--{(cls.option or cls.name).replace('_', '-')}"

    @classmethod
    def due(cls, config, step: int) -> bool:
        every = cls.every(config)
        return bool(every) and step % every == 0

    def run(self, batch: list[ProbeItem], context: ProbeContext) -> list:
        """The payloads of the items in `batch` (all due at this call), in order; None: nothing at that step."""
        raise NotImplementedError

    @staticmethod
    def upright(payload: Any, flip: Callable[[Any], Any] | None) -> Any:
        """The payload for records shown upright: `flip` reverses a camera's (rows, cols) map as the frames are
        turned (None: the camera is upright already)."""
        return payload


_PROBES = PluginRegistry("probe", Probe, BUILTINS, ENTRY_POINTS, ProbeLoadError)
register = _PROBES.register  # add a probe class (usable as a decorator); a taken or empty name is a ValueError
unregister = _PROBES.unregister
registered = _PROBES.registered  # the probe registered for the duration of a block (one defined in a test)


def probes() -> tuple[type[Probe], ...]:
    """Every registered probe, in registration order."""
    return _PROBES.values()


def get(name: str) -> type[Probe]:
    return _PROBES.get(name)


def active(config) -> tuple[type[Probe], ...]:
    """The registered probes `config` (a PolicyConfig) turns on."""
    return tuple(cls for cls in probes() if cls.every(config))


def option_classes() -> tuple[type, ...]:
    """The options dataclasses of the registered probes, in registration order (harness.policy assembles
    PolicyConfig from them)."""
    return tuple(cls.options for cls in probes() if cls.options is not None)


def option_fields(cls: type[Probe]) -> tuple[str, ...]:
    """The names of a probe's own option fields (its `options`, and the field that turns it on)."""
    names = [f.name for f in dataclasses.fields(cls.options)] if cls.options is not None else []
    return tuple(dict.fromkeys(names + ([cls.option] if cls.option else [])))


def measuring_fields() -> tuple[str, ...]:
    """The option fields of every probe that never changes actions: two runs that differ only in these executed the
    same actions, and measured different things beside them (`compare`, `regress` and the provenance line)."""
    return tuple(name for cls in probes() if not cls.changes_actions for name in option_fields(cls))


def measured(policy: dict) -> tuple[str, ...]:
    """The probes a recorded policy block (a protocol's "policy": its sparse fields, only those set) turns on."""
    return tuple(cls.name for cls in probes()
                 if (cls.option is None or policy.get(cls.option) not in (None, 0, False, "")))


def part(probe: type[Probe] | str, what: str) -> Any:
    """A probe's sink, reader, section or layer (None when it declares none); "module:Name" (or "module": the module
    itself) is imported here, a module starting with "." relative to the probe's package."""
    cls = get(probe) if isinstance(probe, str) else probe
    if what not in PARTS:
        raise ValueError(f"a probe part is one of {', '.join(PARTS)}, got {what!r}")
    value = getattr(cls, what)
    if isinstance(value, str):
        module, _, attr = value.partition(":")
        value = importlib.import_module(module, package=cls.__module__)
        value = getattr(value, attr) if attr else value
    return value


def parts(what: str) -> list[tuple[type[Probe], Any]]:
    """(probe, its part) of every registered probe that declares `what`, in registration order."""
    return [(cls, part(cls, what)) for cls in probes() if getattr(cls, what) is not None]

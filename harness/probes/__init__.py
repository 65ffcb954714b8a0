"""The per-step probes: measures a closed-loop run takes at inferred steps, beside the actions, never changing them.

The contract and the registry live in `harness.probes.registry` (this package re-exports its public names); the
built-in probes are its subpackages (attribution, controls, reliance, readout_features, action_consistency), each one
folder that imports the registry and is imported by it only by name, on first use. A probe of another package registers through the entry-point group
`octo_harness.probes` (see the registry's docstring).
"""

from harness.probes.registry import (  # noqa: F401
    BUILTINS, ENTRY_POINTS, PARTS, Probe, ProbeContext, ProbeItem, ProbeLoadError, active, get, measured,
    measuring_fields, option_classes, option_fields, part, parts, probes, register, registered, unregister)

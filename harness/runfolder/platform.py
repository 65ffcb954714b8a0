"""Provenance of a run: the machine, libraries and renderer its numbers came from, and a fingerprint of what
changes those numbers.

Closed-loop trajectories are exactly reproducible only on one platform: XLA:CPU compiles for the host's
instruction set (`XLA_FLAGS=--xla_cpu_max_isa=...` changes the bits), MuJoCo reproduces exactly only on one
build and architecture, and llvmpipe renders differently across CPUs and Mesa versions. So every manifest
records `platform` (CPU vendor, model, the ISA flags that change numerics, cores, OS and kernel, Python,
jax/jaxlib and the XLA device, `XLA_FLAGS`, MuJoCo/robosuite/numpy, the GL backend with its vendor,
renderer and version strings, the render device asked for and the EGL device) and `platform_fingerprint`, a sha256 over the numerics-relevant part
(`NUMERICS`; and the side a suite of the run's tasks records under its name, e.g. LIBERO's own environment, with the
keys it names: envs.suites.Suite.platform, platform_numerics): two runs with equal fingerprints should give bit-identical episodes; with different ones only
replayed inputs and statistics can be compared (`octo-harness replay`, `compare`).
"""

from __future__ import annotations

import hashlib
import json
import os
import platform as _platform
from pathlib import Path

# CPU features XLA:CPU and the BLAS kernels choose code paths by (a subset of /proc/cpuinfo's flags)
NUMERIC_CPU_FLAGS = ("sse4_1", "sse4_2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512dq", "avx512bw", "avx512vl",
                     "avx512_vnni", "avx512_bf16", "avx512_fp16", "avx_vnni", "amx_bf16", "amx_tile", "amx_int8")
# dotted keys of `platform_info()` that change numbers (the fingerprint covers exactly these)
NUMERICS = ("machine", "cpu.vendor", "cpu.model", "cpu.numeric_flags", "jax.version", "jax.jaxlib", "jax.backend",
            "jax.device_kind", "xla_flags", "versions.mujoco", "versions.robosuite", "versions.numpy",
            "gl.backend", "gl.vendor", "gl.renderer", "gl.version")


def cpu_info(cpuinfo: str | None = None) -> dict:
    """{vendor, model, numeric_flags (sorted), cores} from /proc/cpuinfo text (read when None)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        if ":" in line:
            key, value = (part.strip() for part in line.split(":", 1))
            fields.setdefault(key, value)  # the first processor describes the machine
    flags = set(fields.get("flags", "").split())
    return {"vendor": fields.get("vendor_id") or _platform.processor() or "unknown",
            "model": fields.get("model name") or "unknown",
            "numeric_flags": sorted(flags & set(NUMERIC_CPU_FLAGS)),
            "cores": os.cpu_count()}


def gl_info(backend: str | None = None) -> dict:
    """{backend, vendor, renderer, version} of an offscreen GL context made with MuJoCo's backend (MUJOCO_GL);
    `error` instead of the strings when no context can be made (the run fails later with the fix)."""
    backend = (backend if backend is not None else os.environ.get("MUJOCO_GL", "")).strip().lower() or "default"
    out: dict = {"backend": backend,
                 # where rendering was asked to happen (--render-device; "auto": MuJoCo's choice) and the EGL device
                 "render_device": os.environ.get("OCTO_HARNESS_RENDER_DEVICE", "").strip().lower() or "auto",
                 "egl_device_id": os.environ.get("MUJOCO_EGL_DEVICE_ID") or None}
    from envs.gl import context_strings

    out.update(context_strings())  # vendor, renderer, version; or error when no context can be made
    return out


def jax_info() -> dict:
    import jax
    import jaxlib

    device = jax.devices()[0]
    return {"version": jax.__version__, "jaxlib": jaxlib.__version__, "backend": jax.default_backend(),
            "device_kind": getattr(device, "device_kind", str(device)), "devices": jax.device_count()}


def versions() -> dict:
    import mujoco
    import numpy
    import robosuite

    return {"mujoco": mujoco.__version__, "robosuite": robosuite.__version__, "numpy": numpy.__version__,
            "python": _platform.python_version()}


def suite_platforms(tasks) -> dict:
    """{suite name: its side of the platform} for the suites of `tasks` that record one (envs.suites.Suite.platform:
    LIBERO's package, robosuite, MuJoCo, numpy, Python and GL renderer, from its own environment); {} for none."""
    from envs import suites

    sides = {suite.name: suite.platform() for suite in suites.of_tasks(tasks)}
    return {name: side for name, side in sides.items() if side is not None}


def platform_info(gl: dict | None = None, sides: dict | None = None) -> dict:
    """Everything `NUMERICS` names, plus OS, kernel and Python (see the module docstring); `sides`: the sides the
    run's suites record (`suite_platforms`), each under its suite's name and fingerprinted (`suite_numerics`)."""
    uname = _platform.uname()
    return {
        **(sides or {}),
        "machine": uname.machine,
        "os": f"{uname.system} {uname.release}",
        "kernel": uname.version,
        "python": _platform.python_version(),
        "cpu": cpu_info(),
        "jax": jax_info(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "versions": versions(),
        "gl": gl if gl is not None else gl_info(),
    }


def _get(info: dict, dotted: str):
    value = info
    for part in dotted.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    return value


def numerics(info: dict) -> dict:
    """The numerics-relevant part of a platform_info dict: {dotted key: value} (a suite's side's keys too when the
    run has that side, so the fingerprints of runs without one are unchanged)."""
    keys = NUMERICS + suite_numerics(info)
    return {key: _get(info, key) for key in keys}


def suite_numerics(info: dict) -> tuple[str, ...]:
    """The dotted keys of the suites' sides `info` holds that enter the fingerprint (envs.suites.Suite.platform_numerics,
    under the suite's name)."""
    from envs import suites

    return tuple(f"{suite.name}.{key}" for suite in suites.suites() if suite.platform_numerics
                 and isinstance(info.get(suite.name), dict) for key in suite.platform_numerics)


def platform_fingerprint(info: dict) -> str:
    """"sha256:<hex>" over `numerics(info)` (canonical JSON)."""
    text = json.dumps(numerics(info), sort_keys=True, separators=(",", ":"), default=str)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def platform_differences(a: dict | None, b: dict | None) -> list[str]:
    """Numerics-relevant keys whose values differ between two platform_info dicts (all of them when one is missing)."""
    if not isinstance(a, dict) or not isinstance(b, dict):
        return list(NUMERICS)
    na, nb = numerics(a), numerics(b)
    return [key for key in dict.fromkeys([*na, *nb]) if na.get(key) != nb.get(key)]


def git_commit(root: Path | None = None) -> str | None:
    """Commit of the harness checkout (or of the checkout at `root`), read from .git without starting a process (a
    worktree's .git is a file naming its own git folder, whose `commondir` holds the shared refs)."""
    git = (root or Path(__file__).resolve().parents[2]) / ".git"
    try:
        if git.is_file():  # a worktree: "gitdir: <path>"
            git = (git.parent / git.read_text().strip().removeprefix("gitdir:").strip()).resolve()
        common = (git / (git / "commondir").read_text().strip()).resolve() if (git / "commondir").is_file() else git
        head = (git / "HEAD").read_text().strip()
        if not head.startswith("ref: "):
            return head
        ref = head[5:]
        for folder in (git, common):
            if (folder / ref).exists():
                return (folder / ref).read_text().strip()
        for line in (common / "packed-refs").read_text().splitlines():
            if line.endswith(" " + ref):
                return line.split()[0]
    except (OSError, ValueError):
        pass
    return None

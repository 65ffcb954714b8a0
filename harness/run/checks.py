"""Checks before anything heavy: each raises ValueError (or FileNotFoundError) with one line naming the fix.

`check_environment` and `check_destination` run before the model loads; `check_model` right after it,
before the first episode. Numbers (episodes, max steps, seed, ensemble weight) are checked where the
protocol is built (`Protocol.__post_init__`), task names in `settings.resolve_tasks`.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Mapping

import numpy as np

from harness.run.protocol import Protocol

# MuJoCo's rendering backends on Linux: egl and osmesa are headless, glfw/glx need a display
GL_BACKENDS = ("egl", "osmesa", "glfw", "glx")
MAX_RUN_NAME = 255  # bytes: NAME_MAX of ext4, xfs, btrfs, tmpfs and NFS

log = logging.getLogger(__name__)


def check_environment(environ: Mapping[str, str] | None = None) -> None:
    """An unknown MUJOCO_GL value: one line naming the valid ones (MuJoCo would fail at import, after loading)."""
    environ = os.environ if environ is None else environ
    value = environ.get("MUJOCO_GL", "").strip().lower()
    if value and value not in GL_BACKENDS:
        raise ValueError(f"MUJOCO_GL={environ['MUJOCO_GL']!r} is not a rendering backend; use one of "
                         f"{', '.join(GL_BACKENDS)} (egl or osmesa on headless servers) or leave it unset")
    check_accelerator(environ)


def check_accelerator(environ: Mapping[str, str] | None = None) -> None:
    """JAX_PLATFORMS=cuda (or gpu) on a machine where JAX finds no CUDA GPU: one line naming the fix, before the
    model loads (JAX would fail deep inside loading). Without JAX_PLATFORMS, JAX uses a GPU where it finds one."""
    environ = os.environ if environ is None else environ
    value = environ.get("JAX_PLATFORMS", "").strip().lower()
    if not {p.strip() for p in value.split(",")} & {"cuda", "gpu"}:
        return
    import jax

    try:
        jax.devices("gpu")
    except Exception as e:  # RuntimeError, or (jax 0.7 without a CUDA plugin) a bare AssertionError
        if not any(_module_exists(m) for m in ("jax_plugins.xla_cuda12", "jax_cuda12_plugin")):
            cause = "jax's CUDA 12 plugin is not installed"
        else:
            cause = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"JAX_PLATFORMS={value} asks for a GPU but JAX finds none ({cause}); on an NVIDIA machine "
                         "pip install 'octo-harness[cuda]' (and the NVIDIA driver), else unset JAX_PLATFORMS to run "
                         "on the CPU") from None


def check_suites(protocol: Protocol) -> None:
    """Each suite of the protocol's tasks checks what it must before anything loads (envs.suites.Suite.check: LIBERO's
    environment is set up and every episode seed names a stored initial state): one line naming the fix."""
    from envs import suites

    for suite, specs in suites.of_tasks(protocol.tasks).items():
        suite.check(specs, protocol.seed, protocol.seed + protocol.episodes - 1)


def _module_exists(name: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:  # its parent package is missing
        return False


def check_run_name(name: str) -> str:
    """A run name is a plain folder name: no path separators, not '.'/'..', not hidden, not empty, no control
    characters (a newline would split every line-based record and listing that names the run)."""
    if not isinstance(name, str) or not name.strip():
        raise ValueError("--run-name is empty; pass a plain folder name such as lift_eval")
    if any(ord(c) < 32 or ord(c) == 127 for c in name) or name != name.strip():
        raise ValueError(f"--run-name {name!r} holds control characters or surrounding spaces; pass a plain folder "
                         "name such as lift_eval")
    if "/" in name or "\\" in name or "\0" in name or name in (".", "..") or name.startswith(".") or ".." in name:
        raise ValueError(f"--run-name {name!r} is not a plain folder name (no '/', no '..', not starting with '.'); "
                         "choose the parent folder with --out")
    if len(name.encode()) > MAX_RUN_NAME:
        raise ValueError(f"--run-name is {len(name.encode())} bytes long, more than a folder name may be "
                         f"({MAX_RUN_NAME} bytes on common filesystems); choose a shorter name")
    return name


def check_destination(out: Path) -> Path:
    """--out exists or can be created, is a folder and is writable (probed with a real file)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a folder; pass a folder for the runs")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"--out {out} cannot be created ({e.strerror or e}); pass a writable folder") from None
    probe = out / f".octo-harness-probe.{os.getpid()}"
    try:
        with open(probe, "wb") as f:
            f.write(b"ok")
    except OSError as e:
        raise ValueError(f"--out {out} is not writable ({e.strerror or e}); pass a writable folder") from None
    finally:
        try:
            probe.unlink()
        except OSError:
            pass
    return out


def decode_goal_images(folder: str | Path) -> dict[str, np.ndarray]:
    """<folder>/<key>.png -> {key: (height, width, 3) uint8}; one line naming a file that does not decode."""
    from PIL import Image, UnidentifiedImageError

    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"--goal-images {folder} is not a folder; pass a folder holding image_primary.png, ...")
    images = {}
    for path in sorted(folder.glob("*.png")):
        try:
            with Image.open(path) as image:
                images[path.stem] = np.asarray(image.convert("RGB"))
        except (UnidentifiedImageError, OSError, ValueError) as e:
            raise ValueError(f"goal image {path} does not decode as an image ({type(e).__name__}); replace or remove it") from None
    return images


def check_attention_flags(protocol: Protocol, model) -> list[str]:
    """For a policy without what a run computes (harness.policies.Capabilities): PolicyLacksError (one line, exit 2)
    when the protocol asks for a computation the policy lacks (an intervention, rollout attention, a per-step probe that
    runs in the inference);
    else, for a policy without attention, the console line saying its attention outputs are left out. Output options
    only choose how attention is drawn (PNG steps and layers, colour map, overlays, bounding boxes): without attention
    there is nothing to draw, so they are left out with that line, never refused (a baseline's protocol, inherited by
    `regress`, may set any of them)."""
    from harness.probes import registry as probes

    wanted = {}
    policy = protocol.policy
    if policy.intervention is not None:
        wanted["--intervene"] = "interventions"
    if policy.full_attention:
        wanted["--video-attention rollout"] = "attention"
    for probe in probes.active(policy):
        if probe.in_inference(policy):  # a probe its sink computes from the step records needs nothing of the policy
            wanted[probe.inference_flag(policy)] = "probes"
    model.require(wanted)
    if model.capabilities.attention:
        return []
    return [f"{model.source} gives no attention: its episodes have no attention PNGs, overlay panels or attention "
            "measures, whatever the output options say (frames, actions and everything else are recorded)"]


def check_model(protocol: Protocol, model, goal_images: Mapping[str, np.ndarray] | None) -> list[str]:
    """Model-dependent checks; returns the task inputs the episodes will use (["language"], ["goal"] or both)."""
    for line in check_attention_flags(protocol, model):
        log.info("%s", line)
    layers = model.attention_shape.layers if model.attention_shape is not None else 0
    for layer in (protocol.outputs.layers or ()) if layers else ():
        if not -layers <= layer < layers:
            raise ValueError(f"--layers {layer} is out of range: {model.source} has {layers} layers (0..{layers - 1}, "
                             "or negative from the end)")
    va = protocol.outputs.video_attention
    if layers and isinstance(va, int) and not -layers <= va < layers:
        raise ValueError(f"--video-attention {va} is out of range: {model.source} has {layers} layers (0..{layers - 1}) "
                         "or use 'rollout'")
    cameras = list(model.image_sizes)
    unknown = [c for c in protocol.outputs.video_cameras or () if c not in cameras]
    if unknown and (protocol.outputs.video or protocol.outputs.gif):
        raise ValueError(f"--video-cameras {','.join(unknown)}: {model.source} reads no such camera; choose from "
                         f"{','.join(cameras)} (or 'all')")
    policy = protocol.policy
    if policy.execution == "receding_horizon" and policy.receding_steps > model.action_horizon:
        raise ValueError(f"--receding-steps {policy.receding_steps} exceeds the action horizon of {model.source} "
                         f"({model.action_horizon}); choose 1..{model.action_horizon}")
    takes_language = model.takes_language
    goal_keys = sorted(model.goal_image_sizes)
    expected = ", ".join(k + ".png" for k in goal_keys)
    inputs = ["language"] if takes_language else []
    if goal_images is not None:
        if not goal_keys:
            raise ValueError(f"{model.source} takes no goal images; drop --goal-images")
        if not set(goal_images) & set(goal_keys):
            raise FileNotFoundError(f"no goal images in {protocol.goal_images}; expected {expected}")
        inputs.append("goal")
    elif not takes_language and goal_keys:  # a policy taking neither (a scripted one) is asked nothing
        raise ValueError(f"{model.source} is goal-conditioned (no language input); pass --goal-images DIR holding {expected}")
    return inputs


def check_perturbations(protocol) -> None:
    """Every task of the protocol can take its perturbations (envs.perturbations.check_task): one line if not,
    before the model loads or any episode runs."""
    if not protocol.perturb:
        return
    import envs
    from envs.perturbations import check_task, parse_perturb

    perturbations = parse_perturb(protocol.perturb)
    for name in protocol.tasks:
        task = envs.get_task(name)
        cameras = protocol.env.cameras
        keys = tuple(c[0] for c in cameras) if cameras is not None else tuple(s.key for s in envs.parse_cameras(None, task))
        check_task(task, perturbations, keys, protocol.instruction)

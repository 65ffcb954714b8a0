"""Headless OpenGL: choose EGL or OSMesa before MuJoCo loads, and fail with one actionable line.

MuJoCo and PyOpenGL read `MUJOCO_GL` / `PYOPENGL_PLATFORM` when they are first imported, so the choice
has to be made before `robosuite` is imported: `configure()` runs when `envs` is imported and only fills
in variables the user left unset (EGL when an EGL display initialises in a short-lived child process,
else OSMesa when its library is present). `ensure_context()` then imports MuJoCo and creates and frees one real GL context whenever an
environment is made, turning a missing driver into a `HeadlessGLError` that names the apt packages.

`OCTO_HARNESS_RENDER_DEVICE` (`--render-device cpu|gpu|N`) chooses where MuJoCo renders, independently of where JAX
computes: `cpu` renders with Mesa's llvmpipe while JAX uses the GPU (EGL rendering and CUDA compute on one GPU
aborted in 4 of 4 runs in another harness's measurements), `N` renders on EGL device N (another GPU).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import inspect
import os
import subprocess
import sys
from collections.abc import Callable, MutableMapping
from pathlib import Path

APT_EGL = "apt-get install -y libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libgl1 libglib2.0-0"
APT_OSMESA = "apt-get install -y libosmesa6"
_EGL_PLATFORM_DEVICE_EXT = 0x313F


class HeadlessGLError(RuntimeError):
    """No headless OpenGL backend works on this machine."""


def egl_display_works() -> bool:
    """True when libEGL loads and a device display initialises (probed through ctypes, no PyOpenGL)."""
    try:
        lib = ctypes.CDLL(ctypes.util.find_library("EGL") or "libEGL.so.1")
    except OSError:
        return False
    get_proc = lib.eglGetProcAddress
    get_proc.restype = ctypes.c_void_p
    get_proc.argtypes = [ctypes.c_char_p]
    query_ptr = get_proc(b"eglQueryDevicesEXT")
    display_ptr = get_proc(b"eglGetPlatformDisplayEXT")
    if not query_ptr or not display_ptr:
        return False
    query_devices = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(ctypes.c_int))(
        query_ptr
    )
    platform_display = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p)(display_ptr)
    devices = (ctypes.c_void_p * 16)()
    count = ctypes.c_int(0)
    if not query_devices(16, devices, ctypes.byref(count)):
        return False
    lib.eglInitialize.restype = ctypes.c_uint
    lib.eglInitialize.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int)]
    for device in devices[: count.value]:
        display = platform_display(_EGL_PLATFORM_DEVICE_EXT, device, None)
        major, minor = ctypes.c_int(0), ctypes.c_int(0)
        if display and lib.eglInitialize(display, ctypes.byref(major), ctypes.byref(minor)):
            return True
    return False


def egl_display_works_isolated(timeout_s: float = 20.0) -> bool:
    """`egl_display_works` run in a child interpreter, so this process never initialises EGL before a fork."""
    code = (
        "import ctypes, ctypes.util\n"
        f"_EGL_PLATFORM_DEVICE_EXT = {_EGL_PLATFORM_DEVICE_EXT}\n"
        + inspect.getsource(egl_display_works)
        + "\nraise SystemExit(0 if egl_display_works() else 1)\n"
    )
    try:
        return subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=timeout_s).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


def osmesa_library_found() -> bool:
    """True when libOSMesa can be loaded."""
    name = ctypes.util.find_library("OSMesa")
    if name is None:
        return False
    try:
        ctypes.CDLL(name)
    except OSError:
        return False
    return True


def choose_backend(
    environ: MutableMapping[str, str],
    egl_works: Callable[[], bool] = egl_display_works_isolated,
    osmesa_found: Callable[[], bool] = osmesa_library_found,
) -> str:
    """The backend to use: the user's `MUJOCO_GL` if set, else "egl" if it works, else "osmesa" if present, else "egl"."""
    chosen = environ.get("MUJOCO_GL", "").strip().lower()
    if chosen:
        return chosen
    if egl_works():
        return "egl"
    if osmesa_found():
        return "osmesa"
    return "egl"  # nothing works; `ensure_context` will raise the actionable error


RENDER_DEVICE = "OCTO_HARNESS_RENDER_DEVICE"  # cpu | gpu | N (`--render-device`); unset: MuJoCo's own choice
MESA_EGL_VENDOR = "/usr/share/glvnd/egl_vendor.d/50_mesa.json"  # libglvnd's file for Mesa's EGL (libegl-mesa0)
render_device_error: str | None = None  # why the asked-for render device could not be set up (ensure_context raises it)


def render_device_settings(choice: str, environ: MutableMapping[str, str],
                           mesa_vendor: str = MESA_EGL_VENDOR, osmesa_found: Callable[[], bool] | None = None
                           ) -> dict[str, str]:
    """The variables that make MuJoCo render on `choice`, checked against what the user set (HeadlessGLError, one line):

    cpu   Mesa's llvmpipe: EGL through libglvnd's Mesa vendor only (a GPU's EGL driver is never loaded) with
          LIBGL_ALWAYS_SOFTWARE=1, else OSMesa (always the CPU); JAX keeps whatever device it computes on.
    gpu   EGL on the first EGL device (robosuite's default; CUDA_VISIBLE_DEVICES narrows it).
    N     EGL on EGL device N (MUJOCO_EGL_DEVICE_ID=N): render on another GPU than the one JAX computes on.
    """
    choice = str(choice).strip().lower()
    user = environ.get("MUJOCO_GL", "").strip().lower()
    if choice == "cpu":
        if user == "osmesa" or (user in ("", "egl") and not Path(mesa_vendor).is_file()
                                and (osmesa_found or osmesa_library_found)()):
            return {"MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"}
        if user in ("", "egl") and Path(mesa_vendor).is_file():
            return {"MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl", "__EGL_VENDOR_LIBRARY_FILENAMES": mesa_vendor,
                    "LIBGL_ALWAYS_SOFTWARE": "1"}
        if user not in ("", "egl"):
            raise HeadlessGLError(f"--render-device cpu renders with Mesa (EGL or OSMesa) but MUJOCO_GL={user} is set; "
                                  "unset MUJOCO_GL or drop --render-device")
        raise HeadlessGLError(f"--render-device cpu needs Mesa's EGL ({mesa_vendor}) or OSMesa; fix: "
                              f"`apt-get install -y libegl-mesa0` or `{APT_OSMESA}`")
    if choice == "gpu" or choice.isdigit():
        if user not in ("", "egl"):
            raise HeadlessGLError(f"--render-device {choice} renders with EGL on a GPU but MUJOCO_GL={user} is set; "
                                  "unset MUJOCO_GL, or use --render-device cpu to render with Mesa")
        settings = {"MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl"}
        if choice.isdigit():
            given = environ.get("MUJOCO_EGL_DEVICE_ID")
            if given not in (None, "", choice):
                raise HeadlessGLError(f"--render-device {choice} but MUJOCO_EGL_DEVICE_ID={given} is set; keep one of them")
            settings["MUJOCO_EGL_DEVICE_ID"] = choice
        return settings
    raise HeadlessGLError(f"render device {choice!r}: use cpu, gpu or an EGL device number (0, 1, ...)")


def configure(environ: MutableMapping[str, str] | None = None) -> str:
    """Fill in `MUJOCO_GL` and `PYOPENGL_PLATFORM` where unset (or, with OCTO_HARNESS_RENDER_DEVICE, set what that
    device needs: `render_device_settings`); returns the backend in use. Never raises: a render device that cannot
    be set up is kept in `render_device_error` for `ensure_context` (and the command line) to report."""
    global render_device_error
    environ = os.environ if environ is None else environ
    render_device_error = None
    if environ.get(RENDER_DEVICE, "").strip():
        try:
            environ.update(render_device_settings(environ[RENDER_DEVICE], environ))
        except HeadlessGLError as exc:
            render_device_error = str(exc)
    backend = choose_backend(environ)
    environ.setdefault("MUJOCO_GL", backend)
    if backend in ("egl", "osmesa"):
        environ.setdefault("PYOPENGL_PLATFORM", backend)
    return backend


def error_message(backend: str, cause: BaseException | str) -> str:
    """One line: what failed and the apt line (or environment variables) that fix it."""
    return (
        f"headless OpenGL unavailable (MUJOCO_GL={backend}: {str(cause).splitlines()[0] if str(cause) else type(cause).__name__}); "
        f"fix: `{APT_EGL}` for EGL, or `{APT_OSMESA}` and set MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa"
    )


def ensure_context(backend: str | None = None, create: bool = True) -> None:
    """Import MuJoCo and (when `create`) create and free one GL context; raise `HeadlessGLError` on failure.

    MuJoCo loads the `MUJOCO_GL` backend at import time, so a missing library already fails there.
    """
    if render_device_error is not None:
        raise HeadlessGLError(render_device_error)
    backend = (backend or os.environ.get("MUJOCO_GL", "egl")).strip().lower()
    try:
        import mujoco  # noqa: F401

        if not create:
            return
        if backend == "egl":
            from robosuite.renderers.context.egl_context import EGLGLContext as GLContext
        elif backend == "osmesa":
            from robosuite.renderers.context.osmesa_context import OSMesaGLContext as GLContext
        else:
            from robosuite.renderers.context.glfw_context import GLFWGLContext as GLContext
        context = GLContext(max_width=64, max_height=64, device_id=-1)
        context.make_current()
        context.free()
    except Exception as exc:  # any driver/library failure becomes the one actionable line
        if "MUJOCO_EGL_DEVICE_ID" in str(exc):  # --render-device N names a device this machine lacks
            raise HeadlessGLError(f"render device {os.environ.get('MUJOCO_EGL_DEVICE_ID')}: {str(exc).splitlines()[0]} "
                                  "choose an EGL device this machine has (--render-device 0, 1, ...) or "
                                  "--render-device cpu") from exc
        raise HeadlessGLError(error_message(backend, exc)) from exc


def context_strings() -> dict:
    """{vendor, renderer, version} of an offscreen MuJoCo GL context made with this process's MUJOCO_GL, or
    {error: one line} when none can be made (provenance: never raises). The run's platform record
    (harness.runfolder.platform) and the LIBERO server (envs/libero_server.py, in its own environment) both read it."""
    out: dict = {}
    try:
        import mujoco
        from OpenGL import GL

        context = mujoco.GLContext(1, 1)
        context.make_current()
        try:
            for name, enum in (("vendor", GL.GL_VENDOR), ("renderer", GL.GL_RENDERER), ("version", GL.GL_VERSION)):
                value = GL.glGetString(enum)
                out[name] = value.decode(errors="replace") if value else None
        finally:
            context.free()
    except Exception as exc:  # noqa: BLE001 - provenance only
        out["error"] = f"{type(exc).__name__}: {exc}".splitlines()[0]
    return out

"""Live Rerun viewers: a native viewer on this machine (`spawn`) or a web viewer served for a headless one (`serve`),
and the checks they need before anything heavy (a display, free ports). Recordings stream to a viewer's gRPC url
(harness.outputs.rerun_sink.RerunSink's `connect`); `serve_file` serves a saved recording (`octo-harness view`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

from harness.outputs.rerun_sink import APPLICATION_ID, import_rerun

DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090


@dataclass
class LiveViewer:
    """A viewer recordings stream to: `url` is the gRPC address each episode's recording connects to."""

    mode: str  # "spawn" | "serve"
    url: str
    web_url: str | None = None  # serve: open this in a browser (through an SSH tunnel of both ports on a server)
    hub: Any = field(default=None, repr=False)  # serve: the recording stream that hosts the gRPC server (kept alive)


NO_DISPLAY = "no display here for a viewer window; pass --serve (web viewer, prints its URL) or --save PATH.rrd"


def has_display() -> bool:
    """A native viewer window can open: not Linux, or DISPLAY / WAYLAND_DISPLAY set."""
    import sys

    return sys.platform != "linux" or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def check_port(port: int, option: str) -> int:
    """`port` within 1..65535 and free on this machine (nothing listens on it), else one line naming `option`: a
    viewer on a busy port aborted the whole process (a Rust panic, exit 134), a port out of range was a traceback."""
    import errno
    import socket

    if not isinstance(port, int) or isinstance(port, bool) or not 1 <= port <= 65535:
        raise ValueError(f"{option} takes a port number 1-65535, got {port!r}")
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("", port))
    except OSError as exc:
        if exc.errno in (errno.EADDRINUSE, errno.EACCES):
            why = "is in use by another process" if exc.errno == errno.EADDRINUSE else "needs privileges here"
            raise ValueError(f"port {port} ({option}) {why}; pass {option} with a free port") from None
        raise
    finally:
        sock.close()
    return port


def check_viewer(mode: str, grpc_port: int | None = None, web_port: int | None = None) -> None:
    """What a live viewer needs, before anything heavy: a display for spawn (the same line as `view`'s), free ports."""
    if mode == "spawn" and not has_display():
        raise ValueError(NO_DISPLAY)
    check_port(grpc_port or DEFAULT_GRPC_PORT, "--viewer-port")
    if mode == "serve":
        check_port(web_port or DEFAULT_WEB_PORT, "--web-port")


def start_viewer(mode: str, grpc_port: int | None = None, web_port: int | None = None, host: str = "127.0.0.1",
                 blueprint=None) -> LiveViewer:
    """spawn: start the native Rerun viewer on this machine (it listens on `grpc_port`);
    serve: host a gRPC server in this process and the web viewer over HTTP (`web_port`); both on `host`.
    `check_viewer` first: no display for spawn, or a port out of range or in use, is one line (ValueError)."""
    check_viewer(mode, grpc_port, web_port)
    rr = import_rerun()
    port = grpc_port or DEFAULT_GRPC_PORT
    if mode == "spawn":
        rr.spawn(port=port, connect=False, hide_welcome_screen=True)
        return LiveViewer("spawn", f"rerun+http://{host}:{port}/proxy")
    if mode != "serve":
        raise ValueError(f"a live viewer is spawn or serve; got {mode!r}")
    hub = rr.RecordingStream(APPLICATION_ID, recording_id="octo-harness-live")
    url = hub.serve_grpc(grpc_port=port, default_blueprint=blueprint)
    web = web_port or DEFAULT_WEB_PORT
    rr.serve_web_viewer(web_port=web, open_browser=False, connect_to=url)
    return LiveViewer("serve", url, f"http://{host}:{web}/?url={quote(url, safe='')}", hub)


def serve_file(path: str | Path, grpc_port: int | None = None, web_port: int | None = None,
               host: str = "127.0.0.1") -> LiveViewer:
    """Serve a saved recording to the web viewer (for `octo-harness view --serve`): the file is streamed into a
    gRPC server in this process (kept while the process runs)."""
    import_rerun()  # one clear line when rerun-sdk is missing, before a port is taken
    viewer = start_viewer("serve", grpc_port, web_port, host)
    viewer.hub.log_file_from_path(Path(path))
    viewer.hub.flush()
    return viewer

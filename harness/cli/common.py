"""What the subcommands share: the one-line argparse parser, one-line error text, the option groups declared once
(verbose, execution, render device, viewer ports, gate options) and writing a gate's outputs (exit 2 on a refused
disk, never a verdict)."""

from __future__ import annotations

import argparse
import sys

from harness.options import add_arguments

ECHO_LIMIT = 1000  # characters of one error line: a value echoed from a 50 MB input is cut, with its length said
VERBOSE_HELP = "also show other libraries' INFO lines and start-up warnings"


def one_line(message, limit: int = ECHO_LIMIT) -> str:
    """An error's text as one line, cut to `limit` characters (a 50 MB bad value never floods the terminal)."""
    text = " ".join(str(message).splitlines())
    return text if len(text) <= limit else f"{text[:limit - 40]}... (cut: {len(text)} characters in all)"


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors as one line naming the option and the fix (exit 2), not a usage block."""

    FIXES = (("invalid int value", "pass a whole number"), ("invalid float value", "pass a number"),
             ("invalid choice", "pick one of the choices listed"), ("expected one argument", "give it a value"),
             ("required", "add them"), ("unrecognized arguments", "drop them or check the spelling"))

    def error(self, message: str):
        fix = next((fix for text, fix in self.FIXES if text in message), "fix that option")
        self.exit(2, f"error: {self.prog}: {one_line(message.splitlines()[0] if message else message, 300)}; {fix} "
                     f"(see {self.prog} --help)\n")


def add_verbose(parser: argparse.ArgumentParser, top: bool = False) -> None:
    """--verbose, declared once: before the command (octo-harness --verbose run) or after it (run, regress)."""
    where = {"help": VERBOSE_HELP + " (hidden by default)"} if top else {"default": argparse.SUPPRESS, "help": VERBOSE_HELP}
    parser.add_argument("--verbose", action="store_true", **where)


def add_gate_options(parser: argparse.ArgumentParser, command: str, keys: tuple[str, ...]) -> None:
    """The gate options `keys` (harness.gate.config.GateConfig's fields: --max-drop, --alpha, --fail-on, ...)."""
    from harness.gate.config import GateConfig

    add_arguments(parser, (GateConfig,), command, only=keys,
                  overrides={k: {"default": getattr(GateConfig, k)} for k in ("max_drop", "alpha", "first_steps",
                                                                           "fail_on")})


def port(text: str) -> int:
    try:
        number = int(text)
    except ValueError:
        number = None
    if number is None or not 1 <= number <= 65535:
        raise argparse.ArgumentTypeError(f"takes a port number 1-65535, got {text[:40]!r}")
    return number


VIEWER_PORTS = {"run": ("--rerun spawn/serve: the viewer's gRPC port [{grpc}]; serve's web viewer uses --web-port",
                        "--rerun serve: the web viewer's HTTP port [{web}]"),
                "view": ("the viewer's gRPC port [{grpc}]", "--serve: the web viewer's HTTP port [{web}]")}


def add_viewer_ports(parser: argparse.ArgumentParser, command: str) -> None:
    """--viewer-port and --web-port of a live Rerun viewer (run --rerun spawn|serve, view); their [defaults] are the
    viewer's own (None: not given, so a port without a live viewer is refused)."""
    from harness.outputs.rerun_viewer import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT

    grpc, web = (text.format(grpc=DEFAULT_GRPC_PORT, web=DEFAULT_WEB_PORT) for text in VIEWER_PORTS[command])
    parser.add_argument("--viewer-port", type=port, default=None, metavar="PORT", help=grpc)
    parser.add_argument("--web-port", type=port, default=None, metavar="PORT", help=web)


def _render_device(text: str) -> str:
    value = text.strip().lower()
    if value in ("cpu", "gpu") or value.isdigit():
        return value
    raise argparse.ArgumentTypeError(f"--render-device takes cpu, gpu or an EGL device number, got {text!r}")


def add_render_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--render-device", type=_render_device, default=None, metavar="cpu|gpu|N",
                        help="where MuJoCo renders, whatever device JAX computes on: cpu (Mesa llvmpipe: the safe choice "
                             "when JAX uses the GPU), gpu (EGL on the first GPU) or N (EGL device N); recorded in the "
                             "manifest's platform.gl [MuJoCo's choice]")


def apply_render_device(choice: str | None) -> None:
    """Before anything imports MuJoCo: OCTO_HARNESS_RENDER_DEVICE for envs.gl (worker processes inherit it); a
    device that cannot be set up is one line (HeadlessGLError, exit 2)."""
    if choice is None:
        return
    import os

    if "envs" in sys.modules:  # already configured (an in-process caller): configure again with the choice
        os.environ["OCTO_HARNESS_RENDER_DEVICE"] = choice
        from envs import gl

        gl.configure()
    else:
        os.environ["OCTO_HARNESS_RENDER_DEVICE"] = choice
        from envs import gl
    if gl.render_device_error is not None:
        raise gl.HeadlessGLError(gl.render_device_error)


def add_execution_args(parser: argparse.ArgumentParser) -> None:
    """Where a run's episodes execute (not part of the protocol: a run may resume with another worker count); the
    flags' None is 'not given' (so --policy-replicas without ray is refused), their [defaults] the executor's own."""
    from harness.run.execution import DEFAULT_EXECUTOR, DEFAULT_REPLICAS

    parser.add_argument("--workers", type=int, default=None,
                        help="env worker processes, inference batched in one process (same episodes as a sequential run) "
                             "[none: sequential; with --executor ray: the CPU count, minus one per replica on a cluster]")
    parser.add_argument("--executor", choices=["local", "ray"], default=None,
                        help="where the env workers run: local processes or Ray actors (pip install 'octo-harness[ray]') "
                             f"[{DEFAULT_EXECUTOR}]")
    parser.add_argument("--ray-address", default=None,
                        help="Ray cluster to join (e.g. auto or head-node:6379); --out must be on a filesystem every node "
                             "mounts [start a local Ray instance]")
    parser.add_argument("--policy-replicas", type=int, default=None,
                        help=f"Ray: model replicas serving the env workers [{DEFAULT_REPLICAS}]")


def execution(args):
    """The executor factory the execution flags of `add_execution_args` ask for (None: sequential)."""
    from harness.run.execution import executor_factory

    return executor_factory(args.workers, args.executor, args.ray_address, args.policy_replicas)


class OutputsNotWritten(RuntimeError):
    """A gate's verdict was reached but its output files could not be written (exit 2: never read as a verdict)."""


def writing(what: str, verdict: str, write):
    """`write()`, or OutputsNotWritten (one line, exit 2) when the disk refuses (full, read-only, permissions): exit 1
    would read as REGRESSED / CHANGED."""
    try:
        return write()
    except OSError as exc:
        reason = exc.strerror or str(exc).splitlines()[0] or type(exc).__name__
        raise OutputsNotWritten(f"could not write {what}: {reason}; the verdict was {verdict}, but without its files "
                                "it does not count: free space or pass --out on another disk, then run it again") from None


def keep_serving(viewer, what: str = "the web viewer keeps serving") -> None:
    """The web viewer lives in this process: keep it until Ctrl-C (as `rerun --serve-web` does)."""
    import time

    print(f"{what}; Ctrl-C to stop", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:  # the way to stop serving, not an interruption of the command
        from harness import interrupts

        interrupts.reset()

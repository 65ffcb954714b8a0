"""Command line: `octo-harness run ...` (closed-loop evaluation with attention capture) and `octo-harness tasks`.

Only parses arguments into frozen configs, wires the runner and prints; user errors are one line. One module per
subcommand (`add_parser(subparsers)` and `main(args)`, chosen with `set_defaults(func=...)`); the option groups they
share live in `common.py`; the options of runs and gates are fields of their configs (harness/options.py).
"""

from __future__ import annotations

import errno
import gc
import signal
import sys
import threading
from pathlib import Path

from harness.cli import compare, diagnose, regress, replay, report, robustness, run, sanity, serve, tasks, view
from harness.cli.common import OneLineParser, OutputsNotWritten, add_verbose, apply_render_device, one_line

USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, KeyError, FileNotFoundError, PermissionError)
# An unexpected exception in any command (a bug): its own code, never 1 (a verdict for compare and regress, "an episode
# failed" for run) nor 2 (bad input). docs/running.md#exit-codes
INTERNAL_ERROR = 5
DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)  # a write the disk refused
COMMANDS = (run, tasks, robustness, report, diagnose, compare, replay, view, sanity, regress, serve)  # in --help's order


def _user_errors() -> tuple[type[BaseException], ...]:
    from envs import suites
    from envs.gl import HeadlessGLError
    from harness.octo.errors import OctoError
    from harness.run.space import DiskFullError
    from harness.run.store import ResultsWriteError, RunLockedError

    # ResultsWriteError, DiskFullError: a full disk under regress's candidate run is exit 2, never 1 (REGRESSED)
    return (*USER_ERRORS, RunLockedError, OctoError, HeadlessGLError, OutputsNotWritten, ResultsWriteError,
            DiskFullError, *suites.errors())


def _interrupt(signum, frame):
    """SIGINT / SIGTERM before the run installs its own handler (loading the model, compiling): the same exit as
    later, recorded first so a KeyboardInterrupt swallowed by a finaliser is not lost (harness.interrupts)."""
    from harness import interrupts

    interrupts.handler(signum, frame)


def _name(command) -> str:
    return command.__name__.rsplit(".", 1)[-1]  # each module is named as its command


def build_parser(command: str | None = None) -> OneLineParser:
    """The command line's parser; with `command`, that command's options only (every other command a bare entry of
    its name, never shown: a command line naming `command` parses the same, without importing what the others'
    options are declared in, such as run's the simulators and JAX for `tasks` or `report`)."""
    parser = OneLineParser(prog="octo-harness", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show tracebacks for errors")
    add_verbose(parser, top=True)
    sub = parser.add_subparsers(dest="command", required=True)
    for module in COMMANDS:
        if command is None or _name(module) == command:
            module.add_parser(sub)
        else:
            sub.add_parser(_name(module))
    return parser


def named_command(argv: list[str]) -> str | None:
    """The command `argv` names (its first word that is not an option: the top level's options take no value), or
    None where there is none, it is not a command, or help is asked for before it (the whole parser is needed)."""
    for word in argv:
        if word in ("-h", "--help", "--") or not word.startswith("-"):
            return word if word in {_name(module) for module in COMMANDS} else None
    return None


def _origin(exc: BaseException) -> str:
    """ ' (at module.py:123)' of the innermost frame that raised, for a bug report."""
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return f" (at {Path(tb.tb_frame.f_code.co_filename).name}:{tb.tb_lineno})" if tb is not None else ""


def main(argv: list[str] | None = None) -> int:
    from harness import console, interrupts

    # the handler goes in before anything is parsed: building the parser imports the simulators, and a Ctrl-C there
    # would meet Python's default handler, whose KeyboardInterrupt an importer may swallow (the command then went on
    # to exit 0) or turn into a traceback with exit 1
    interrupts.reset()
    main_thread = threading.current_thread() is threading.main_thread()
    previous = {s: signal.signal(s, _interrupt) for s in (signal.SIGINT, signal.SIGTERM)} if main_thread else {}
    unraisable = sys.unraisablehook
    sys.unraisablehook = interrupts.quiet_unraisable(unraisable)  # a swallowed Ctrl-C: the one line, no traceback
    try:
        args = build_parser(named_command(sys.argv[1:] if argv is None else argv)).parse_args(argv)
        console.configure(args.verbose)
        interrupts.check()  # a signal while parsing whose KeyboardInterrupt was swallowed
        code = _dispatch(args)
        interrupts.check()  # a signal whose KeyboardInterrupt a finaliser swallowed: still 128 + signum
        return code
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", 2)
        print(interrupted_line(signum, argv if argv is not None else sys.argv[1:]), file=sys.stderr)
        return 128 + signum
    finally:
        if interrupts.received is not None:  # what the interrupt left half-built is finalised under the quiet hook
            gc.collect()
        sys.unraisablehook = unraisable
        interrupts.settle()  # no signal re-sent after an import may outlive the handlers restored below
        for s, handler in previous.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)


RESUMABLE = ("run", "robustness", "regress")  # the commands that record episodes in the run store


def interrupted_line(signum: int, argv) -> str:
    """The one line a signal ends a command with; the commands that record episodes say how to resume (read from
    argv: the signal may land before the arguments are parsed)."""
    line = f"interrupted ({'SIGTERM' if signum == 15 else 'SIGINT'})"
    command = next((a for a in argv if not a.startswith("-")), None)
    return line + ("; finished episodes are recorded, run the same command to resume" if command in RESUMABLE else "")


def _dispatch(args) -> int:
    """The command, its errors as exit codes: 2 for bad input or a full disk, INTERNAL_ERROR for a bug."""
    try:
        apply_render_device(getattr(args, "render_device", None))
        return args.func(args)
    except _user_errors() as exc:
        if args.debug:
            raise
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"error: {one_line(message)}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a read-only filesystem, a quota: one line (exit 2), never a verdict
        if exc.errno not in DISK_ERRORS:
            return _internal_error(exc, args)
        if args.debug:
            raise
        where = f" {exc.filename}" if exc.filename else " its outputs"
        print(f"error: could not write{where}: {exc.strerror or exc}; free space (or pass --out on another disk) and "
              f"run the same command again", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - the one place a bug becomes an exit code that is no verdict
        return _internal_error(exc, args)


def _internal_error(exc: BaseException, args) -> int:
    """A bug: one line saying so (the traceback with --debug), exit INTERNAL_ERROR."""
    if args.debug:
        import traceback

        traceback.print_exception(exc)
    where = _origin(exc)
    print(f"internal error: {type(exc).__name__}: {one_line(exc, 300)}{where}; please report it (run with "
          f"octo-harness --debug {args.command} ... for the traceback); exit {INTERNAL_ERROR}", file=sys.stderr)
    return INTERNAL_ERROR

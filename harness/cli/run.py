"""`octo-harness run`: run (or resume) the closed-loop episodes of a protocol into one run folder.

Its options are the fields of harness.run.settings.RUN_OPTIONS (protocol, env, policy, output, statistics and
destination options, each declared once on its field); here only what controls the command itself (protocol file,
resume, overwrite, execution, render device, the live viewer)."""

from __future__ import annotations

import sys
from pathlib import Path

from harness.cli.common import add_execution_args, add_render_arg, add_verbose, add_viewer_ports, execution, keep_serving
from harness.options import add_arguments, find, options


def _retries(value) -> int:
    """--retries from the flag or the protocol file, checked (one line, exit 2)."""
    from harness.run.protocol import Recovery

    return find([Recovery], "retries").convert(value)


def _classes():
    from harness.run.settings import RUN_OPTIONS

    return [cls for cls, _ in RUN_OPTIONS]


def add_parser(sub) -> None:
    r = sub.add_parser("run", help="run (or resume) closed-loop episodes and record attention",
                       description="Run the episodes of an evaluation protocol into <out>/<run-name>; running the same "
                                   "command again resumes it. Defaults are shown in brackets.")
    r.add_argument("--protocol", type=Path, default=None,
                   help="TOML file whose keys mirror these flags (task, model, episodes, ...); flags given here override it")
    r.add_argument("--resume", type=Path, default=None, metavar="RUN_DIR",
                   help="continue the run in RUN_DIR with the protocol from its manifest.json")
    r.add_argument("--overwrite", action="store_true", help="start the run afresh, deleting what the run folder holds")
    r.add_argument("--retry-failed", action="store_true", help="on resume, run episodes that failed with an error again")
    add_arguments(r, _classes())
    add_viewer_ports(r, "run")
    add_verbose(r)
    add_execution_args(r)
    add_render_arg(r)
    r.set_defaults(func=main)


def _live_viewer(args, modes: tuple[str, ...]):
    """--rerun modes -> the live viewer started for spawn / serve, or None. A missing viewer extra is one line."""
    from harness.outputs.rerun_sink import import_rerun
    from harness.outputs.rerun_viewer import start_viewer

    if (args.viewer_port is not None or args.web_port is not None) and not {"spawn", "serve"} & set(modes):
        raise ValueError("--viewer-port and --web-port need --rerun spawn or --rerun serve")
    if modes:
        import_rerun()
    live = next((m for m in modes if m in ("spawn", "serve")), None)
    if live is None:
        return None
    viewer = start_viewer(live, args.viewer_port, args.web_port)
    if live == "serve":
        print(f"Rerun web viewer: {viewer.web_url}  (on a remote server: ssh -L {args.web_port or 9090}:localhost:"
              f"{args.web_port or 9090} -L {args.viewer_port or 9876}:localhost:{args.viewer_port or 9876} <server>)",
              flush=True)
    else:
        print(f"Rerun viewer spawned; episodes stream to {viewer.url}", flush=True)
    return viewer


def _protocol(args, given: dict):
    """(protocol, out, run name, ci method, retries, preflight mode, space check) from the manifest of --resume RUN_DIR, or from
    --protocol and the flags (--retries, --preflight and --no-space-check are taken with --resume too: they are not part of
    the protocol)."""
    from harness.run import RunStore
    from harness.run.preflight import PreflightOptions
    from harness.run.protocol import protocol_from_manifest
    from harness.run.settings import build_protocol, out_dir, read_protocol_file

    retries = given.pop("retries", None)
    preflight = given.pop("preflight", None)
    skip_space = given.pop("no_space_check", None)  # not part of the protocol: taken with --resume too
    if args.resume is None:
        settings = {**(read_protocol_file(args.protocol) if args.protocol else {}), **given}
        retries = retries if retries is not None else settings.get("retries")
        return (build_protocol(settings), out_dir(settings), settings.get("run_name"), settings.get("ci_method"),
                _retries(retries) if retries is not None else None,
                PreflightOptions(preflight or settings.get("preflight") or "warn").mode,
                not (skip_space or settings.get("no_space_check")))
    if given or args.protocol is not None:
        raise ValueError(f"--resume takes the protocol from {args.resume}/manifest.json; drop "
                         + ", ".join("--" + k.replace("_", "-") for k in (given or {"protocol": 1})))
    manifest = RunStore(args.resume).read_manifest()
    if manifest is None:
        raise FileNotFoundError(f"{args.resume} holds no manifest.json; pass the folder of an octo-harness run")
    protocol = protocol_from_manifest(manifest, args.resume / "manifest.json", model_fingerprint=None,
                                      goal_fingerprint=None)
    preflight = preflight or (manifest.get("preflight") or {}).get("mode") or "warn"
    return protocol, args.resume.parent, args.resume.name, None, retries, preflight, not skip_space  # None: recorded


def main(args) -> int:
    from harness.outputs.rerun_sink import parse_modes
    from harness.run import ResultsWriteError, execute
    from harness.run.space import DiskFullError

    factory = execution(args)
    modes = parse_modes(args.rerun)  # a bad --rerun is one line, before anything heavy
    given = {o.key: getattr(args, o.key) for _, o in options(*_classes())
             if o.key != "rerun" and getattr(args, o.key) is not None}
    if "save" in modes:
        given["rerun"] = True  # an output option of the protocol (spawn and serve are not)
    protocol, out, name, method, retries, preflight, space_check = _protocol(args, given)
    viewer = _live_viewer(args, modes)
    try:
        summary = execute(protocol, out, name, overwrite=args.overwrite, retry_failed=args.retry_failed, ci_method=method,
                          executor=factory, viewer=viewer.url if viewer is not None else None, retries=retries,
                          preflight=preflight, space_check=space_check)
    except DiskFullError as exc:  # the run stopped where its disk filled: no verdict on the episodes left (exit 2)
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ResultsWriteError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if summary.skipped:
        print(f"resumed: {summary.skipped} of {len(summary.manifest['jobs'])} episodes were already finished")
    print(summary.table())
    if summary.manifest["model"].get("is_random"):
        print(f"NOTE: {summary.manifest['model']['source']} has random weights; this run checks the pipeline, not Octo's behaviour.")
    print(f"results: {summary.run_dir}")
    code = 0 if all(r.status == "ok" for r in summary.rows) else 1
    if viewer is not None and viewer.mode == "serve":
        keep_serving(viewer, "run finished; the web viewer keeps serving its recordings")
    return code

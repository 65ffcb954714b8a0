"""`octo-harness view`: one episode of a finished run in the Rerun viewer (spawned, served, or saved as .rrd)."""

from __future__ import annotations

from pathlib import Path

from harness.cli.common import add_viewer_ports, keep_serving


def add_parser(sub) -> None:
    vw = sub.add_parser("view", help="open an episode of a finished run in the Rerun viewer (pip install 'octo-harness[viewer]')",
                        description="Scrub one episode: frames, every layer's and head's attention, attribution maps, "
                                    "actions, rewards and measures on one timeline. A run made with --rerun save is "
                                    "opened as recorded; otherwise the recording is rebuilt from the run's files and the "
                                    "frames re-simulated from the episode's seed (checked bit for bit against the "
                                    "recorded actions). See docs/viewer.md.")
    vw.add_argument("run", type=Path, metavar="RUN_DIR")
    vw.add_argument("--task", default=None, help="task of the episode [the run's first]")
    vw.add_argument("--episode", type=int, default=None, help="episode index within the task [the first finished]")
    vw.add_argument("--save", type=Path, default=None, metavar="PATH",
                    help="write the recording to PATH (.rrd; open later with `rerun PATH`) instead of opening a viewer")
    vw.add_argument("--serve", action="store_true",
                    help="serve the web viewer from this machine (a headless server) and print its URL; Ctrl-C stops it")
    vw.add_argument("--no-simulate", action="store_true",
                    help="do not re-simulate the episode for its frames: maps and measures only")
    vw.add_argument("--model", default=None, metavar="SOURCE",
                    help="the run's policy from elsewhere, to re-simulate with: a served run's server (ws://HOST:PORT: "
                         "a run does not record the address) or a copy of its checkpoint [the run's own]")
    vw.add_argument("--served-conventions", default=None, type=Path, metavar="FILE",
                    help="with --model ws://: the conventions file the run was made with (its content is in the run's "
                         "model fingerprint, its path is not recorded)")
    add_viewer_ports(vw, "view")
    vw.set_defaults(func=main)


def main(args) -> int:
    import tempfile

    from harness.outputs.rerun_sink import import_rerun
    from harness.outputs.rerun_viewer import check_viewer, serve_file, start_viewer
    from harness.gate.view import build_recording

    rr = import_rerun()
    if args.save is not None and args.save.suffix != ".rrd":
        raise ValueError(f"--save {args.save}: a Rerun recording's name ends in .rrd")
    if args.serve or args.save is None:  # before the episode is rebuilt: no display, a port out of range or in use
        check_viewer("serve" if args.serve else "spawn", args.viewer_port, args.web_port)
    simulate = not args.no_simulate
    if (args.model is not None or args.served_conventions is not None) and not simulate:
        raise ValueError("--model and --served-conventions load the policy to re-simulate the frames with; "
                         "--no-simulate re-simulates nothing: drop one")
    if args.served_conventions is not None and not str(args.model or "").startswith("ws://"):
        raise ValueError("--served-conventions goes with --model ws://HOST:PORT (a served run's server)")
    if args.save is not None or args.serve:
        with tempfile.TemporaryDirectory() as scratch:
            target = args.save or Path(scratch) / "episode.rrd"
            result = build_recording(args.run, args.task, args.episode, save=target, simulate=simulate,
                                     model_source=args.model, served_conventions=args.served_conventions)
            print(f"{result.episode.task} episode {result.episode.episode}: frames: {result.frames}")
            if args.save is not None:
                print(f"recording: {result.path}  (open it with: rerun {result.path})")
            if args.serve:
                viewer = serve_file(result.path, args.viewer_port, args.web_port)
                keep_serving(viewer, f"Rerun web viewer: {viewer.web_url}")
        return 0
    viewer = start_viewer("spawn", args.viewer_port)
    result = build_recording(args.run, args.task, args.episode, connect=viewer.url, simulate=simulate,
                             model_source=args.model, served_conventions=args.served_conventions)
    if result.source == "recording":
        stream = rr.RecordingStream("octo-harness", recording_id=f"file:{result.path}")
        stream.connect_grpc(viewer.url)
        stream.log_file_from_path(result.path)
        stream.flush(blocking=True)
    print(f"{result.episode.task} episode {result.episode.episode} sent to the viewer; frames: {result.frames}")
    return 0

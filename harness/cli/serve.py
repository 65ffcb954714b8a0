"""`octo-harness serve`: a checkpoint behind openpi's websocket protocol (harness/policies/server.py), until Ctrl-C."""

from __future__ import annotations

import argparse



def _port(text: str) -> int:
    number = int(text) if text.strip().isdigit() else -1
    if not 0 <= number <= 65535:
        raise argparse.ArgumentTypeError(f"takes a port number 0-65535 (0: a free one), got {text[:40]!r}")
    return number


def _positive(text: str) -> int:
    number = int(text) if text.strip().isdigit() else 0
    if number < 1:
        raise argparse.ArgumentTypeError(f"takes a whole number >= 1, got {text[:40]!r}")
    return number


def add_parser(sub) -> None:
    # imported here, not at the top: `from harness.cli import main` stays light, so the Ctrl-C handler is in before
    # numpy and the policies load (tests/runfolder/test_hostile_inputs.py)
    from harness.policies.server import DEFAULT_MAX_BATCH

    sv = sub.add_parser("serve", help="serve a checkpoint over openpi's websocket protocol (evaluate it elsewhere with "
                                      "--model ws://HOST:PORT)",
                        description="Load a policy and answer inference requests over a websocket (openpi's protocol "
                                    "and the harness's batched extension; pip install 'octo-harness[served]'). Prints "
                                    "'serving MODEL (fingerprint ...) on ws://HOST:PORT' when ready; Ctrl-C or "
                                    "SIGTERM stops it (exit 0). A busy port is one line, exit 2. See docs/serving.md.")
    sv.add_argument("--model", required=True, help="the checkpoint to serve: a folder, hf://owner/name or random:PRESET")
    sv.add_argument("--port", type=_port, required=True, help="the TCP port to listen on (0: a free one, printed)")
    sv.add_argument("--host", default="127.0.0.1",
                    help="the address to listen on; 0.0.0.0 serves other machines, with no authentication [127.0.0.1]")
    sv.add_argument("--max-batch", type=_positive, default=DEFAULT_MAX_BATCH,
                    help=f"requests one extension frame may carry (declared in the metadata) [{DEFAULT_MAX_BATCH}]")
    sv.add_argument("--inference-batch", type=_positive, default=None,
                    help="examples per compiled inference call (part of the served fingerprint) [the checkpoint's "
                         "harness.toml, else 1]")
    sv.add_argument("--dataset-key", default=None,
                    help="dataset statistics to unnormalise actions with (part of the served fingerprint) [the "
                         "checkpoint's harness.toml, else its default]")
    sv.set_defaults(func=main)


def main(args) -> int:
    from harness.policies.server import bind, serve_until_stopped, server_for

    sock = bind(args.host, args.port)  # a busy port fails here, before the model loads
    try:
        server = server_for(args.model, {"inference_batch": args.inference_batch, "dataset_key": args.dataset_key},
                            args.max_batch)
    except BaseException:
        sock.close()
        raise
    serve_until_stopped(server, sock, args.model)
    return 0

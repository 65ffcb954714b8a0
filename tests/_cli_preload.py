"""Imported by tests/forked_cli.py's forkserver: the command line's modules, parser included (no JAX backend starts,
nothing renders)."""

from harness.cli import build_parser

build_parser()

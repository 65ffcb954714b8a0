"""The reference policies' command lines from dataclass fields, as the harness builds its own (harness.options).

Each option is one field declared with `harness.options.option(default, flag, help, ...)` on the dataclass that owns
it: `TrainConfig` (steps, batch size, learning rate, seed, warm start), `DaggerConfig` (task, episodes, step limit),
`Workers` and `Provenance` below, and each command's own options dataclass (`PipelineOptions`, `LiberoPipelineOptions`,
`ProbeOptions`, `DaggerOptions`, `EvaluateOptions`, `ClosedLoopOptions`). The parser's flags come from those fields,
and each help's `[default]` from the field's default (`harness.options.Option.help_for`), so no command copies a
default. A field without a default is a required option. A default of None or "" means "not given": its
`default_text` says what that means (the recipe's value, every task), and `values` leaves the field at None or "".
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

from harness.options import option, option_of, options


@dataclass(frozen=True)
class Workers:
    workers: int = option(2, "--workers", "processes that record or run the episodes (spawned; the data do not "
                                          "depend on their number)", type=int)

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise ValueError(f"--workers {self.workers}: give 1 or more processes")


@dataclass(frozen=True)
class Provenance:
    """What an evaluation table says of how it was made (reference_policies.evaluate, libero_eval closed-loop)."""
    note: str = option("", "--note", "text placed above the table (command, checkpoint step, ...)", default_text="none")
    command: str | None = option(None, "--command", "the command to name in the provenance line (a script that calls "
                                                    "this one)", default_text="this command")


def default_of(field: dataclasses.Field) -> Any:
    """The field's default (its factory's value), or MISSING for a required field."""
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return dataclasses.MISSING


def add_options(parser, classes: Iterable, command: str = "run", only: Iterable[str] | None = None,
                overrides: Mapping[str, Mapping[str, Any]] | None = None) -> None:
    """The flags of the fields of `classes` (or those named in `only`, in that order) on `parser` (or an argument
    group): argparse's own default is None, so `parse` tells a given value from the field's default."""
    found = {f.name: f for cls in classes for f, _ in options(cls)}
    for name in (only if only is not None else list(found)):
        field = found[name]
        extra = dict((overrides or {}).get(name, {}))
        if default_of(field) is dataclasses.MISSING:
            extra.setdefault("required", True)
        option_of(field).add_to(parser, command, **extra)


def values(cls, args: argparse.Namespace, skip: Iterable[str] = ()) -> dict[str, Any]:
    """{field name: value} of the fields of `cls` given on the command line (None = not given)."""
    given = vars(args)
    return {f.name: given[o.key] for f, o in options(cls)
            if f.name not in skip and given.get(o.key) is not None}


def parse(parser: argparse.ArgumentParser, cls, argv: list[str] | None, **fixed):
    """(the namespace, `cls` built from it): a value its `__post_init__` refuses is the parser's one-line error
    (exit 2) before anything heavy loads."""
    args = parser.parse_args(argv)
    try:
        return args, cls(**{**values(cls, args), **fixed})
    except ValueError as e:
        parser.error(str(e))

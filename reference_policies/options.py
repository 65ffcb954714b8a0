"""The reference policies' command lines from dataclass fields, as the harness builds its own (harness.options).

Each option is one field declared with `harness.options.option(default, flag, help, ...)` on the dataclass that owns
it: `TrainConfig` (steps, batch size, learning rate, seed, warm start), `DaggerConfig` (task, episodes, step limit),
`Workers` and `Provenance` below, and each command's own options dataclass (`PipelineOptions`, `LiberoPipelineOptions`,
`ProbeOptions`, `DaggerOptions`, `EvaluateOptions`, `ClosedLoopOptions`). The parser's flags come from those fields,
and a help text's `[default]` from the field's default, so no command copies a default. A field without a default
is a required option. A default of None or "" means "not given": its help says in brackets what that means (the
recipe's value, every task), and `parse` leaves the field at None or "".
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
    note: str = option("", "--note", "text placed above the table (command, checkpoint step, ...) [none]")
    command: str | None = option(None, "--command", "the command to name in the provenance line (a script that calls "
                                                    "this one) [this command]")


def default_of(field: dataclasses.Field) -> Any:
    """The field's default (its factory's value), or MISSING for a required field."""
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return dataclasses.MISSING


def shown(value: Any) -> str:
    """A default as its help text shows it: 0.0006 as 6e-4's `g` form, text as it is."""
    return format(value, "g") if isinstance(value, float) else str(value)


def help_text(field: dataclasses.Field, command: str = "run") -> str | None:
    """The field's help with its default in brackets; a switch, a required option and a None or "" default (whose
    help states what not giving it means) take the help as written."""
    o = option_of(field)
    text, default = o.help_for(command), default_of(field)
    if o.action == "store_true" or default is dataclasses.MISSING or default is None or default == "":
        return text
    return f"{text} [{shown(default)}]" if text else f"[{shown(default)}]"


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
        if option_of(field).action == "store_true":
            extra.setdefault("default", False)
        option_of(field).add_to(parser, command, help=help_text(field, command), **extra)


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

"""Options declared once: every option of a run, its outputs, its statistics or a gate is a field of the frozen
dataclass that owns it, and the field's metadata (an `Option`) holds its flag, help text, protocol-file types, how a
given value becomes the field's value, and whether (and when) it enters the protocol and its hash:

    png_every: int = option(1, "--png-every", "write overlays every n-th step (0 = none)", type=int, file=(int,))

The help's "[default]" is the field's default (`Option.shown`), so the two cannot disagree; where the value alone does
not say it (None: the task's limit), `default_text` words it. The flag names its field: `--png-every` sets
`png_every`; where it does not, the option says so once (`negated`: `--no-video` turns `video` off; `field`:
`--intervene` sets `intervention`), and tests/docs/test_option_tables.py checks both over every command.

The owners: `harness.run.protocol.Protocol` (model, tasks, seeds, ...), `envs.options.EnvOptions` (which, below
`harness`, writes the same metadata as a plain dict), `harness.policy.PolicyConfig`, `harness.outputs.writers.
OutputOptions`, `harness.run.protocol.RunStatistics`, `harness.run.protocol.Recovery` and `harness.run.settings.
Destination` (recorded in the manifest outside the protocol), `harness.gate.config.GateConfig` (compare, regress, replay). From those fields come
the command-line parsers (`add_arguments`), the protocol file's keys (`file_keys`), a settings dict's values for a
dataclass (`given`), what the protocol records (`record`) and the docs' option tables (`table`), so adding an option
is adding one field.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping

KEY = "option"  # the field-metadata key holding an Option (or the plain dict of one)
UNSET = type("Unset", (), {"__repr__": lambda self: "UNSET"})()  # `absent` not declared: the field's default decides


@dataclass(frozen=True)
class Option:
    flag: str  # "--png-every"; the settings / protocol-file key is its name with underscores ("png_every")
    # the --help text, or {command: text} where commands word it apart; without its default, which `help_for` adds
    help: str | Mapping[str, str] | None = None
    file: tuple[type, ...] = ()  # the types a protocol file may hold under the key; () = not a protocol-file key
    hashed: bool = True  # recorded in the protocol (and its hash); False: recorded elsewhere in the manifest
    sparse: bool = False  # recorded only when not at its default, so protocols made before the option keep their hash
    type: Callable | None = None  # argparse type of the flag's text
    choices: tuple | None = None
    metavar: str | None = None
    action: str | None = None  # "store_true" (a switch) or "append" (repeatable)
    convert: Callable[[Any], Any] | None = None  # a given value (flag or protocol file) -> the field's value
    # the field's value when the option is not given, where a run's differs from the dataclass's: only --no-masks (a
    # run renders masks; envs.make, which shares EnvOptions, does not unless asked); any other default is the field's
    absent: Any = UNSET
    doc: str | None = None  # the docs table's text where it says more than the help [the help]
    negated: bool = False  # a switch that turns its field off: --no-video sets `video` False (the key stays no_video)
    field: str | None = None  # the field's name where the flag names it otherwise (--intervene sets `intervention`)
    # the help's [default] where the field's value alone does not say it ("{}" stands for the value), or
    # {command: text}; "" for none
    default_text: str | Mapping[str, str] | None = None
    value: Any = UNSET  # the field's default (filled in from the field)

    @property
    def key(self) -> str:
        return self.flag[2:].replace("-", "_")

    def shown(self, command: str = "run", default: Any = UNSET) -> str | None:
        """The help's [default]: `default` (a command's own, e.g. robustness' 20 episodes) or the field's, as text;
        None for a switch (off unless given) and for a default the help does not state."""
        text = self.default_text.get(command, self.default_text.get("run")) \
            if isinstance(self.default_text, Mapping) else self.default_text
        value = shown(self.value if default is UNSET or default is None else default)
        if text is not None:
            return text.replace("{}", value or "") or None
        return None if self.action == "store_true" else value

    def text_for(self, command: str) -> str | None:
        """The help as written for `command`, without its default."""
        return self.help.get(command, self.help.get("run")) if isinstance(self.help, Mapping) else self.help

    def help_for(self, command: str, default: Any = UNSET) -> str | None:
        """The --help text with its [default] (`shown`)."""
        text = self.text_for(command)
        value = self.shown(command, default)
        if text is None or value is None:
            return text
        return f"{text} [{value}]" if text else f"[{value}]"

    def add_to(self, parser, command: str = "run", **overrides):
        """The flag on `parser` (its argparse action); `overrides` (default, required, metavar, help) where `command`
        differs from run."""
        kwargs: dict[str, Any] = {"default": None, "help": self.help_for(command, overrides.get("default", UNSET))}
        if self.action is not None:
            kwargs["action"] = self.action
        for name in ("type", "metavar"):
            if getattr(self, name) is not None:
                kwargs[name] = getattr(self, name)
        if self.choices is not None:
            kwargs["choices"] = list(self.choices)
        kwargs.update(overrides)
        if kwargs.get("help") is None:
            del kwargs["help"]
        action = parser.add_argument(self.flag, **kwargs)
        action.declared = self  # the option behind the flag (the tests check each help's default against it)
        return action


def shown(value: Any) -> str | None:
    """A default as the help shows it (0.0 -> 0, 3.5e-07 -> 3.5e-7, (0, 5) -> 0,5); None where there is none."""
    if value is UNSET or value is dataclasses.MISSING or value is None or value == "" or isinstance(value, bool):
        return None
    if isinstance(value, float):
        return re.sub(r"e([+-])0*(\d)", lambda m: "e" + m.group(1).replace("+", "") + m.group(2), f"{value:.6g}")
    if isinstance(value, (tuple, list)):
        return ",".join(str(v) for v in value)
    return str(value)


def option(default: Any = dataclasses.MISSING, flag: str = "", help: str | Mapping[str, str] | None = None, *,
           default_factory: Any = dataclasses.MISSING, **details) -> Any:
    """A dataclass field declared with its option (see `Option`)."""
    return dataclasses.field(default=default, default_factory=default_factory,
                             metadata={KEY: Option(flag, help, value=default, **details)})


def option_of(field: dataclasses.Field) -> Option | None:
    found = field.metadata.get(KEY)
    return Option(**found, value=field.default) if isinstance(found, Mapping) else found


def options(*classes) -> list[tuple[dataclasses.Field, Option]]:
    """(field, option) of every field of `classes` that declares one, in declaration order."""
    return [(f, o) for cls in classes for f in dataclasses.fields(cls) if (o := option_of(f)) is not None]


def find(classes: Iterable, key: str) -> Option:
    """The option of `classes` whose settings key is `key`."""
    return next(o for _, o in options(*classes) if o.key == key)


def add_arguments(parser, classes: Iterable, command: str = "run", only: Iterable[str] | None = None,
                  overrides: Mapping[str, Mapping[str, Any]] | None = None, skip: Iterable[str] = ()) -> None:
    """The flags of every option of `classes` (or those whose key is in `only`, in that order) on `parser`."""
    found = {o.key: o for _, o in options(*classes)}
    for key in (only if only is not None else list(found)):
        if key not in skip:
            found[key].add_to(parser, command, **(overrides or {}).get(key, {}))


def file_keys(*classes) -> dict[str, tuple[type, ...]]:
    """{settings key: the types a protocol file may hold there} of every option of `classes` that files may hold."""
    return {o.key: o.file for _, o in options(*classes) if o.file}


def given(cls, settings: Mapping[str, Any], skip: Iterable[str] = ()) -> dict[str, Any]:
    """{field name: value} of `cls` from a settings dict (None = not given): each given option converted (a value
    converted to None, as 'all' layers, is left to the field's default), and the run's own value (`Option.absent`)
    of those not given that declare one."""
    out = {}
    for field, o in options(cls):
        if field.name in skip:
            continue
        value = settings.get(o.key)
        if value is not None and o.negated:
            value = not value
        if value is not None and o.convert is not None:
            value = o.convert(value)
        if value is not None:
            out[field.name] = value
        elif o.absent is not UNSET and settings.get(o.key) is None:
            out[field.name] = o.absent
    return out


def record(instance) -> dict:
    """The fields of an options dataclass as plain data (what the manifest records); a sparse option only when it is
    not at its default."""
    data = dataclasses.asdict(instance)
    for field, o in options(type(instance)):
        if o.sparse and data[field.name] == field.default:
            del data[field.name]
    return data


def _flag_text(o: Option) -> str:
    value = "" if o.action == "store_true" else " " + (o.metavar or ("|".join(o.choices) if o.choices else
                                                                      o.key.upper().split("_")[-1]))
    return f"`{o.flag}{value}`".replace("|", "\\|")


def _where(path: str | None, field: dataclasses.Field, o: Option) -> str:
    if path is None:  # an option that changes no file of the run (the space check)
        return "not recorded (changes no file)"
    if not o.hashed and path.startswith("protocol."):  # a protocol group's presentation field (the colour map)
        path = "presentation"
    where = f"`{path}.{field.name}`" if path else "the run folder's path"
    return where + (" (when set)" if o.sparse else "") + ("" if o.hashed or not path else ", outside the hash")


def table(groups: Iterable[tuple[Any, str]], command: str = "run") -> str:
    """The Markdown table of the options of `groups` ((class, where the manifest records its fields), ...)."""
    lines = ["| option | meaning [default] | recorded as |", "|---|---|---|"]
    for cls, path in groups:
        for field, o in options(cls):
            text = (o.doc or o.help_for(command) or "").replace("|", "\\|").replace("%%", "%")  # a doc words its own
            lines.append(f"| {_flag_text(o)} | {text} | {_where(path, field, o)} |")
    return "\n".join(lines) + "\n"



def joined(value):
    """A list from a protocol file (["a", "b"]) as the command line gives it ("a,b"); text as it is."""
    return ",".join(value) if isinstance(value, list) else value


def layer_list(value) -> tuple[int, ...] | None:
    """--layers 0,5,11 (or a list) -> (0, 5, 11); 'all' -> None (every layer)."""
    if value is None or value == "all":
        return None
    if isinstance(value, str):
        try:
            return tuple(int(x) for x in value.split(","))
        except ValueError:
            raise ValueError(f"layers takes comma-separated layer indices or 'all', got {value!r}") from None
    return tuple(int(x) for x in value)


def camera_list(value) -> tuple[str, ...] | None:
    """--video-cameras image_primary,image_wrist (or a list) -> the keys; None / 'all' -> None (every camera)."""
    if value is None or value == "all":
        return None
    keys = [k.strip() for v in ([value] if isinstance(value, str) else value) for k in str(v).split(",") if k.strip()]
    if not keys:
        raise ValueError(f"--video-cameras takes comma-separated observation keys (e.g. image_primary,image_wrist) or "
                         f"'all'; got {value!r}")
    return tuple(keys)

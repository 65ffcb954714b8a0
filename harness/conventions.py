"""Evaluation conventions a checkpoint records next to its config.json (`harness.toml`), and how they combine
with what the user asks for.

A finetuned Octo checkpoint only works in robosuite when it is evaluated the way it was trained: the
same cameras at the same sizes, the same image orientation, the same action space, the same
normalisation statistics. `harness.toml` (TOML, read with the standard library's `tomllib`) says so:

    # How octo-harness evaluates this checkpoint; every key is optional.
    format = "octo-harness-conventions/1"

    [env]                              # envs.EnvOptions fields a model depends on
    action_space = "robosuite"         # "octo-delta" | "robosuite" | "libero"
    image_convention = "upright"       # "upright" | "opengl" | "rot180"

    [env.cameras]                      # observation key = [robosuite camera, square size]
    image_primary = ["agentview", 84]

    [policy]                           # harness.policy.PolicyConfig fields
    dataset_key = "robosuite_reference"
    action_normalization = "normal"    # "normal" (mean/std) | "bounds" (p01/p99)
    proprio_normalization = "normal"   # "normal" | "bounds" | "none"
    sampler = "latest"                 # "latest" | "v0.1.0" (diffusion heads)
    execution = "receding_horizon"     # and receding_steps, ensemble_weight

    [text]
    tokenizer = "tokenizer"            # "auto" | "fallback" | a tokenizer.json or folder, relative to the checkpoint

Precedence, highest first: command-line flags, the protocol file, `harness.toml`, the default of the task's
family, i.e. its suite (`Suite.defaults`, envs.suites). A missing file means "no conventions": robosuite tasks then take
octo-delta actions and upright images (as before), LIBERO tasks the published evaluation's (OpenVLA's run_libero_eval.py: the
rendered frame turned 180 degrees, LIBERO's action convention; the stored initial states and settle steps are the
LIBERO env's own). A run that mixes families gives each family's tasks its own default (`resolve_env`).
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping

from envs import suites
from envs.options import EnvConfigError, EnvOptions
from harness.bounded import read_toml

CONVENTIONS_FILE = "harness.toml"
FORMAT = "octo-harness-conventions/1"
ENV_KEYS = ("cameras", "image_convention", "action_space", "hold_gripper")  # masks and fast_render are run choices, not model conventions


# a task's family is its suite (envs.suites): its `defaults` are used for a key neither the command line nor harness.toml
# sets, and its `default_note` says why in the console line of a run that uses them
SOURCE_KEYS = ("cameras", "image_convention", "action_space", "hold_gripper")  # the conventions whose source is recorded


def task_family(task: str) -> str:
    """The name of the suite a task (or a name standing for several, e.g. a LIBERO suite's) belongs to (envs.suites)."""
    return suites.of(task).name


def resolve_env(conventions: "CheckpointConventions", given: Mapping[str, Any], families) -> tuple[dict, dict]:
    """({family: EnvOptions}, {family: {key: "flag" | "checkpoint" | "default:<family>"}}) for each family in
    `families`: `given` (the user's choices, None values ignored) over the checkpoint's conventions over the family's
    defaults. A hold_gripper given as "open"/"closed" is read in each family's own action space."""
    given = {k: v for k, v in given.items() if v is not None}
    options, sources = {}, {}
    for family in dict.fromkeys(families):
        options[family] = EnvOptions.from_dict({**suites.get(family).defaults, **conventions.env, **given})
        sources[family] = {k: "flag" if k in given else "checkpoint" if k in conventions.env else f"default:{family}"
                           for k in SOURCE_KEYS if k != "hold_gripper" or options[family].hold_gripper is not None}
    return options, sources


def default_lines(sources: Mapping[str, Mapping[str, str]], options: Mapping[str, EnvOptions], tasks, model: str,
                  has_file: bool) -> list[str]:
    """One console line per family whose image or action convention came from the family's default, e.g.
    `libero_object: rot180 images, libero actions (published protocol; MODEL has no harness.toml)`."""
    lines = []
    for family, keys in sources.items():
        if not any(keys.get(k, "").startswith("default:") for k in ("image_convention", "action_space")):
            continue
        label = suites.get(family).label([t for t in tasks if task_family(t) == family])
        why = f"{model}'s harness.toml does not set them" if has_file else f"{model} has no {CONVENTIONS_FILE}"
        option = options[family]
        lines.append(f"{label}: {option.image_convention} images, {option.action_space} actions "
                     f"({suites.get(family).default_note}; {why})")
    return lines


class ConventionsError(ValueError):
    """A harness.toml that cannot be used (message: one line naming the file and the fix)."""


def _policy_keys() -> tuple[str, ...]:
    from harness.policy import PolicyConfig

    return tuple(f.name for f in fields(PolicyConfig) if f.name != "full_attention")


@dataclass(frozen=True, eq=False)
class CheckpointConventions:
    env: Mapping[str, Any] = field(default_factory=dict)  # subset of ENV_KEYS, as EnvOptions.to_dict writes them
    policy: Mapping[str, Any] = field(default_factory=dict)  # subset of PolicyConfig fields
    source: str | None = None  # the file they were read from
    text_tokenizer: str | None = None  # [text] tokenizer: "auto", "fallback" or a path (absolute once read from a folder)

    @classmethod
    def parse(cls, data: Mapping[str, Any], source: str | None = None) -> "CheckpointConventions":
        where = source or CONVENTIONS_FILE
        unknown = sorted(set(data) - {"format", "env", "policy", "text", "served"})
        if unknown:
            raise ConventionsError(f"{where}: unknown top-level key(s) {unknown}; use format, [env], [policy], [text], "
                                   "[served]")
        text = dict(data.get("text") or {})
        if sorted(text) not in ([], ["tokenizer"]) or not isinstance(text.get("tokenizer", ""), str):
            raise ConventionsError(f"{where}: [text] takes one key, tokenizer = \"auto\" | \"fallback\" | \"<path>\"; "
                                   f"got {text}")
        if data.get("format", FORMAT) != FORMAT:
            raise ConventionsError(f"{where}: format {data.get('format')!r} unsupported; this harness reads {FORMAT!r}")
        env = dict(data.get("env") or {})
        policy = dict(data.get("policy") or {})
        bad_env = sorted(set(env) - set(ENV_KEYS))
        if bad_env:
            raise ConventionsError(f"{where}: [env] key(s) {bad_env} are not checkpoint conventions; allowed: {list(ENV_KEYS)}")
        bad_policy = sorted(set(policy) - set(_policy_keys()))
        if bad_policy:
            raise ConventionsError(f"{where}: [policy] key(s) {bad_policy} unknown; allowed: {list(_policy_keys())}")
        try:
            EnvOptions.from_dict(env)  # validate values now, with the file named
        except EnvConfigError as e:
            raise ConventionsError(f"{where}: {e}") from None
        conventions = cls(env=env, policy=policy, source=source, text_tokenizer=text.get("tokenizer"))
        try:
            conventions.policy_config()
        except ValueError as e:
            raise ConventionsError(f"{where}: {e}") from None
        return conventions

    @classmethod
    def read_file(cls, path: str | Path) -> "CheckpointConventions":
        """The conventions in a harness.toml-format file of any name (--served-conventions); a missing or invalid
        file is one line. Its [served] table is the served-policy client's (harness/policies/served.py)."""
        path = Path(path)
        if not path.is_file():
            raise ConventionsError(f"{path}: no such conventions file; fix --served-conventions")
        try:
            data = read_toml(path)
        except tomllib.TOMLDecodeError as e:
            raise ConventionsError(f"{path}: not valid TOML ({e}); fix the file") from None
        served = data.get("served") if isinstance(data.get("served"), dict) else {}
        stated = {k: served[k] for k in ("image_convention", "action_space") if k in served}  # [served] may state them
        if stated:
            data = {**data, "env": {**stated, **dict(data.get("env") or {})}}
        conventions = cls.parse(data, str(path))
        if conventions.text_tokenizer not in (None, "auto", "fallback"):
            raise ConventionsError(f"{path}: [text] tokenizer is the server's business; drop it from this file")
        return conventions

    @classmethod
    def read(cls, folder: str | Path | None) -> "CheckpointConventions":
        """The conventions in `<folder>/harness.toml`; none (empty) when the folder or file does not exist."""
        if folder is None:
            return cls()
        path = Path(folder) / CONVENTIONS_FILE
        if not path.is_file():
            return cls()
        try:
            data = read_toml(path)
        except tomllib.TOMLDecodeError as e:
            raise ConventionsError(f"{path}: not valid TOML ({e}); fix or delete the file") from None
        conventions = cls.parse(data, str(path))
        tokenizer = conventions.text_tokenizer
        if tokenizer not in (None, "auto", "fallback"):  # a path: relative to the checkpoint folder
            tokenizer = str((Path(folder) / Path(tokenizer).expanduser()).resolve())
            if not Path(tokenizer).exists():
                raise ConventionsError(f"{path}: [text] tokenizer {conventions.text_tokenizer!r} does not exist in "
                                       f"{folder}; fix the path or delete the key")
            conventions = dataclasses.replace(conventions, text_tokenizer=tokenizer)
        return conventions

    def env_options(self, overrides: Mapping[str, Any] | None = None) -> EnvOptions:
        """EnvOptions from these conventions with `overrides` (the user's explicit choices; None values ignored) on top."""
        given = {k: v for k, v in (overrides or {}).items() if v is not None}
        return EnvOptions.from_dict({**self.env, **given})

    def policy_config(self, overrides: Mapping[str, Any] | None = None):
        """PolicyConfig from these conventions with `overrides` (None values ignored) on top."""
        from harness.policy import PolicyConfig

        given = {k: v for k, v in (overrides or {}).items() if v is not None}
        return PolicyConfig(**{**self.policy, **given})

    def to_dict(self) -> dict:
        text = {"text": {"tokenizer": self.text_tokenizer}} if self.text_tokenizer is not None else {}
        return {"format": FORMAT, "env": dict(self.env), "policy": dict(self.policy), **text}

    def to_toml(self) -> str:
        """TOML text of these conventions (strings, numbers, booleans, camera tables)."""
        lines = ["# How octo-harness evaluates this checkpoint; every key is optional (see harness/conventions.py).",
                 f"format = {_toml_value(FORMAT)}", ""]
        env = {k: v for k, v in self.env.items() if k != "cameras" and v is not None}
        cameras = self.env.get("cameras")
        if env or cameras:
            lines.append("[env]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in env.items()]
            lines.append("")
        if cameras:
            lines.append("[env.cameras]")
            lines += [f"{k} = {_toml_value(list(v))}" for k, v in EnvOptions(cameras=cameras).to_dict()["cameras"].items()]
            lines.append("")
        policy = {k: v for k, v in self.policy.items() if v is not None}
        if policy:
            lines.append("[policy]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in policy.items()]
            lines.append("")
        if self.text_tokenizer is not None:
            lines += ["[text]", f"tokenizer = {_toml_value(self.text_tokenizer)}", ""]
        return "\n".join(lines)

    def write(self, folder: str | Path) -> Path:
        """Write `<folder>/harness.toml` (validated by reading it back)."""
        from harness.files import write_atomic

        text = self.to_toml()
        CheckpointConventions.parse(tomllib.loads(text))
        path = Path(folder) / CONVENTIONS_FILE
        write_atomic(path, lambda f: f.write(text.encode()))
        return path


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise ConventionsError(f"cannot write {value!r} ({type(value).__name__}) to {CONVENTIONS_FILE}")

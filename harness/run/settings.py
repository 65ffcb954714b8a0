"""From what the user asked for (command-line flags, a protocol file) to a `Protocol`, parsed once at the edge.

Settings are a flat dict keyed like the `run` command's flags (`max_steps` for `--max-steps`, `task` for
`--task`, ...). A protocol file (`--protocol eval.toml`, read with `tomllib`) holds the same keys (dashes or
underscores) at its top level; flags given on the command line override it; checkpoint conventions
(`<checkpoint>/harness.toml`, see harness/conventions.py) come next, then the task family's defaults
(LIBERO: the published protocol; harness.conventions.FAMILY_DEFAULTS), then the defaults below:

    # eval.toml
    task = ["Lift", "Stack"]          # or "Lift,Stack"
    model = "/models/finetune"
    episodes = 50
    seed = 1000
    max_steps = 200
    execution = "receding_horizon"
    receding_steps = 4
    camera = ["image_primary=agentview:84"]   # or a table: [camera] image_primary = "agentview:84"
    png_every = 0
    fast_render = true
    perturb = "camera:3,lighting:1"   # or ["camera@image_wrist:2", "noise:4"] (envs.perturbations)

An unknown key is a one-line error naming it.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Any, Mapping

from dataclasses import dataclass

from envs.options import EnvOptions
from harness.bounded import read_toml, short
from harness.options import file_keys, given, option
from harness.run.protocol import DEFAULT_MODEL
from harness.policy import PolicyConfig
from harness.measures.attribution import DEFAULT_METHODS
from harness.outputs.writers import ATTRIBUTION_VIDEO
from harness.run.protocol import Protocol, Recovery, RunStatistics
from harness.run.preflight import PreflightOptions
from harness.run.space import SpaceCheck
from harness.outputs.writers import OutputOptions

DEFAULT_OUT = "results/runs"


@dataclass(frozen=True)
class Destination:
    """Where a run's folder goes: `<out>/<run_name>` (its path, not part of the protocol)."""

    out: str = option(DEFAULT_OUT, "--out", "output root", type=Path, file=(str,), hashed=False)
    run_name: str | None = option(
        None, "--run-name", "folder name of this run", file=(str,), hashed=False,
        default_text="<model>_<protocol hash>: the same command resumes the same run",
        doc="the run folder is `DIR/NAME` [`results/runs/<model>_<protocol hash>`, so the same command resumes the "
            "same run]; NAME is a plain folder name")


# The options of `run`, each declared once on the field that holds it, and where the manifest records each class (None:
# nowhere, as it changes no file)
RUN_OPTIONS = ((Protocol, "protocol"), (EnvOptions, "protocol.env"), (PolicyConfig, "protocol.policy"),
               (OutputOptions, "protocol.outputs"), (RunStatistics, "statistics"), (Recovery, "recovery"),
               (PreflightOptions, "preflight"), (SpaceCheck, None), (Destination, ""))
# key -> expected TOML type(s); the same names as the `run` flags (rerun: true writes each episode's episode.rrd;
# live viewers are chosen on the command line)
FILE_KEYS: dict[str, tuple[type, ...]] = file_keys(*(cls for cls, _ in RUN_OPTIONS))


def read_protocol_file(path: str | Path) -> dict[str, Any]:
    """Settings from a TOML protocol file (keys normalised to underscores); one-line errors for bad files and keys."""
    path = Path(path)
    try:
        data = read_toml(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"protocol file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"cannot read protocol file {path}: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"protocol file {path} is not valid TOML: {e}") from None
    settings = {key.replace("-", "_"): value for key, value in data.items()}
    if len(settings) < len(data):
        twice = sorted(k for k in settings if sum(key.replace("-", "_") == k for key in data) > 1)
        raise ValueError(f"protocol file {path}: {', '.join(twice)} given twice (with '-' and with '_'); keep one")
    if "tasks" in settings and "task" not in settings:
        settings["task"] = settings.pop("tasks")
    unknown = sorted(set(settings) - set(FILE_KEYS))
    if unknown:
        raise ValueError(f"protocol file {path}: unknown key(s) {', '.join(unknown)}; "
                         f"known: {', '.join(sorted(FILE_KEYS))}")
    for key, value in settings.items():
        if not isinstance(value, FILE_KEYS[key]) or (isinstance(value, bool) and bool not in FILE_KEYS[key]):
            kinds = " or ".join(t.__name__ for t in FILE_KEYS[key])
            raise ValueError(f"protocol file {path}: {key} must be a {kinds}, got {short(value)}")
    if isinstance(settings.get("layers"), list):
        settings["layers"] = tuple(settings["layers"])
    if isinstance(settings.get("task"), str):
        settings["task"] = [settings["task"]]
    if isinstance(settings.get("camera"), str):
        settings["camera"] = [settings["camera"]]
    if isinstance(settings.get("camera"), dict):
        settings["camera"] = [f"{k}={v}" if isinstance(v, str) else f"{k}={v[0]}:{v[1]}" for k, v in settings["camera"].items()]
    if settings.get("goal_images") is not None:  # relative to the protocol file
        settings["goal_images"] = str((path.parent / settings["goal_images"]).resolve())
    if settings.get("text_tokenizer") not in (None, "auto", "fallback"):  # a tokenizer.json path: relative to the file
        candidate = path.parent / Path(settings["text_tokenizer"]).expanduser()
        if candidate.exists():
            settings["text_tokenizer"] = str(candidate.resolve())
    return settings


def resolve_tasks(values: list[str] | tuple[str, ...] | None) -> tuple[str, ...]:
    """Task names as given (repeated and/or comma-separated; 'all' = every robosuite task; a LIBERO suite name = its
    tasks, "libero_object/3" = one) -> registry names, case-insensitive, deduplicated."""
    from envs.resolver import resolve_names

    names = [t.strip() for v in (values or []) for t in str(v).split(",") if t.strip()]
    if not names:
        raise ValueError("no task given; pass --task NAME (see `octo-harness tasks`)")
    return resolve_names(names)


def _model_folder(model: str) -> Path | None:
    """The local checkpoint folder of a model source (for its harness.toml), or None."""
    if model.startswith("random:"):
        path = Path(model[len("random:"):]).expanduser()
        return path if path.is_dir() else (path.parent if path.is_file() else None)
    if model.startswith("hf://"):
        from harness.octo import checkpoint

        try:
            return checkpoint.resolve_checkpoint_dir(model)
        except Exception:  # not in the cache: loading reports it
            return None
    path = Path(model).expanduser()
    return path if path.is_dir() else None


def _conventions(model: str, served_conventions: str | None = None):
    """The model's conventions: from --served-conventions where its family takes it, else what the policy declares
    of itself (PolicyFamily.declared_conventions: a server's metadata), else its checkpoint folder's harness.toml."""
    from harness.conventions import CheckpointConventions
    from harness.policies import family_of

    family = family_of(model)
    if served_conventions is not None:
        if not family.takes_served_conventions:
            raise ValueError("--served-conventions is for a policy behind a server (--model ws://HOST:PORT); a "
                             "checkpoint's conventions are its harness.toml: drop the flag")
        return CheckpointConventions.read_file(served_conventions)
    declared = family.declared_conventions(model)
    if declared is not None:  # what the policy says of itself (a server's metadata)
        return CheckpointConventions.parse(declared, f"{model} (its metadata)") if declared else CheckpointConventions()
    return CheckpointConventions.read(_model_folder(model))


def normalise_model(model: str) -> str:
    """Local checkpoint paths become absolute (a run's protocol must not depend on the working directory)."""
    from harness.octo import presets

    if model.startswith("hf://") or model[len("random:"):] in presets.preset_names():
        return model
    if model.startswith("random:"):
        return "random:" + str(Path(model[len("random:"):]).expanduser().resolve())
    path = Path(model).expanduser()
    return str(path.resolve()) if path.exists() else model


def build_protocol(settings: Mapping[str, Any]) -> Protocol:
    """A Protocol from explicit settings (None = not given); conventions and defaults fill the rest."""
    s = {k: v for k, v in settings.items() if v is not None}
    model = normalise_model(str(s.get("model", DEFAULT_MODEL)))
    served = s.get("served_conventions")
    conventions = _conventions(model, str(Path(served).expanduser().resolve()) if served else None)

    env_given: dict[str, Any] = given(EnvOptions, s)
    tasks = resolve_tasks(s.get("task"))
    env, family_env, sources = _family_env(conventions, env_given, tasks)

    video_attention = s.get("video_attention", -1)
    policy_given: dict[str, Any] = given(PolicyConfig, s)
    policy_given["full_attention"] = video_attention == "rollout"
    if video_attention in ATTRIBUTION_VIDEO and "attribution" not in s:  # the MP4 shows an attribution map: computed
        methods = DEFAULT_METHODS if s.get("faithfulness_every") else None
        if not methods:
            policy_given["attribution"] = video_attention
        elif video_attention not in methods.split(","):
            policy_given["attribution"] = f"{methods},{video_attention}"
    policy = conventions.policy_config(policy_given)

    outputs = OutputOptions(**given(OutputOptions, s))
    return Protocol(
        model=model,
        tasks=tasks,
        env=env,
        policy=policy,
        outputs=outputs,
        text_tokenizer=text_tokenizer_choice(s.get("text_tokenizer", conventions.text_tokenizer)),
        **given(Protocol, s, skip=("model", "tasks", "text_tokenizer")),
        family_env=family_env,
        convention_sources=sources,
    )


def _family_env(conventions, given: dict[str, Any], tasks) -> tuple[EnvOptions, dict | None, dict | None]:
    """(env options of the first task's family, {other family: the options where its defaults differ} or None,
    {family: {key: source}}): flags over the checkpoint's harness.toml over each family's defaults."""
    from harness.conventions import resolve_env, task_family

    options, sources = resolve_env(conventions, given, [task_family(t) for t in tasks])
    first, *others = options
    base = options[first].to_dict()
    family_env = {f: {k: v for k, v in options[f].to_dict().items() if base.get(k) != v} for f in others}
    return options[first], {f: v for f, v in family_env.items() if v} or None, sources


def text_tokenizer_choice(value: str | None) -> str | None:
    """--text-tokenizer auto|fallback|PATH as the protocol records it: None (auto), "fallback", or an absolute path
    (a name that is no existing path stays as given: a Hugging Face hub repo holding tokenizer.json)."""
    if value is None or value == "auto":
        return None
    if value == "fallback":
        return value
    path = Path(value).expanduser()
    if path.exists():
        return str(path.resolve())
    if value.endswith(".json") or value.startswith(("/", ".", "~")):
        raise FileNotFoundError(f"--text-tokenizer {value}: no such file; pass a tokenizer.json (or a folder holding "
                                "one), 'fallback' or 'auto'")
    return value


def out_dir(settings: Mapping[str, Any]) -> Path:
    return Path(os.path.expanduser(str(settings.get("out") or Destination.out)))

"""The protocol of an evaluation run: everything that decides its episodes, as one frozen, serialisable value.

A run is a `Protocol` (model source and fingerprint of its checkpoint files, tasks, episodes, seeds, max steps,
execution, instruction and goal overrides, env options, output options, harness version, perturbations) plus the list of
episode jobs it implies (`Protocol.jobs()`: `(task, episode index, seed)`, episode k of every task seeded
`seed + k`). Two runs with equal `to_dict()` produce the same files; `protocol_hash` names that value and
`diff` lists the fields (dotted names, e.g. `policy.receding_steps`, `env.cameras`) where two protocols differ.

Nested options are frozen dataclasses owned by their stages (`envs.EnvOptions`, `harness.policy.PolicyConfig`,
`harness.outputs.writers.OutputOptions`); they serialise with their own `to_dict` when they have one, else
`dataclasses.asdict`, so a field added there is recorded, compared and restored here without code changes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from envs.options import EnvOptions
from envs.perturbations import parse_perturb, perturb_text
from harness import probes
from harness.files import json_safe
from harness.options import option, options
from harness.policies import family_of, policy_fingerprint
from harness.policies.fingerprint import checkpoint_files, files_fingerprint, tokenizer_identity  # noqa: F401
from harness.policy import PolicyConfig
from harness.run.jobs import FORMAT, EpisodeJob  # noqa: F401  (re-exported)
from harness.outputs.writers import OutputOptions
from harness.runfolder.schema import FIX, MalformedRunError, check_protocol, flatten, protocol_hash  # noqa: F401



# Bounds checked before anything heavy (docs/run-integrity.md): a run's jobs (tasks x episodes), the largest seed
# any episode resets with (numpy's legacy RandomState and robosuite take seeds below 2**32), and an episode's steps.
MAX_JOBS = 100_000
MAX_SEED = 2**32 - 1
MAX_STEPS = 100_000


def harness_version() -> str:
    try:
        from importlib.metadata import version

        return version("octo-harness")
    except Exception:  # not installed (running from a checkout)
        return "0+unknown"


DEFAULT_MODEL = "hf://rail-berkeley/octo-small-1.5"  # a run's model when none is given (the field has no default)


@dataclass(frozen=True)
class Protocol:
    model: str = option(  # hf://owner/name, a checkpoint folder (absolute path), or random:<preset>
        flag="--model", file=(str,), help={
            "run": "hf://owner/name, a local checkpoint folder, or random:octo-small-1.5 / random:octo-base-1.5",
            "robustness": "model (as for `run --model`)"}, default_text={"run": DEFAULT_MODEL, "robustness": ""})
    tasks: tuple[str, ...] = option(  # registry names, in run order, no duplicates
        flag="--task", file=(str, list), action="append", field="tasks", help={
            "run": "task name (repeat or comma-separate for several); 'robosuite' for every robosuite task ('all' is "
                   "its older name), a LIBERO suite's name for its tasks",
            "robustness": "task name(s), repeat or comma-separate"})
    episodes: int = option(1, "--episodes", {"run": "episodes per task",  # per task
                                             "robustness": "episodes per task and condition"}, type=int, file=(int,))
    seed: int = option(0, "--seed", {"run": "episode k uses seed + k",  # episode k of every task: seed + k
                                     "robustness": "episode k uses seed + k in every condition"},
                       type=int, file=(int,),
                       doc="episode k of each task is reset with seed `S + k` (same seed → same actions, attention, "
                           "images) [0]")
    max_steps: int | None = option(  # None = each task's own limit
        None, "--max-steps", "stop each episode after N control steps", type=int, file=(int,),
        default_text="task's limit")
    instruction: str | None = option(  # override of every task's instruction
        None, "--instruction", "override the task's language instruction", file=(str,))
    goal_images: str | None = option(  # absolute folder holding <obs key>.png goal images
        None, "--goal-images", "folder with <obs key>.png goal images (image_primary.png, ...) for goal-conditioned "
        "models", type=Path, file=(str,), convert=lambda v: str(Path(v).expanduser().resolve()),
        doc="goal-conditioned models: `DIR/image_primary.png`, `DIR/image_wrist.png` (resized to the model's goal "
            "size)")
    env: EnvOptions = field(default_factory=lambda: EnvOptions(masks=True))
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    outputs: OutputOptions = field(default_factory=OutputOptions)
    model_fingerprint: str | None = None  # filled by `fingerprinted()`: sha256 of the checkpoint files, or the preset
    goal_fingerprint: str | None = None  # sha256 of the goal image files
    harness_version: str = field(default_factory=harness_version)
    text_tokenizer: str | None = option(  # None: the checkpoint's own (auto); "fallback"; or an absolute path
        None, "--text-tokenizer", "text tokenizer: the checkpoint's own (t5-base from the Hugging Face cache), the "
        "deterministic fallback (not T5), or a tokenizer.json / folder; part of the model fingerprint",
        file=(str,), metavar="auto|fallback|PATH", sparse=True, default_text="auto",
        doc="the text tokenizer: `auto` the one the checkpoint's config names (t5-base from the Hugging Face cache, or a "
            "tokenizer folder inside the checkpoint), `fallback` the deterministic hash tokenizer (not T5: for running "
            "offline when t5-base is not cached), or a `tokenizer.json` / a folder holding one; also `[text] "
            "tokenizer` in `harness.toml`. The tokenizer's identity (kind, vocabulary size, sha256 of its file) is in "
            "the manifest (`model.tokenizer`) and in the model fingerprint [auto]")
    served_conventions: str | None = option(  # absolute path, or None: the server's own (its metadata)
        None, "--served-conventions", "a policy behind a server (--model ws://): a harness.toml-format file with its "
        "image convention and action space ([env]) and the server's observation keys ([served]); its content is part "
        "of the model fingerprint", file=(str,), metavar="FILE", sparse=True, hashed=False,
        convert=lambda v: str(Path(v).expanduser().resolve()), default_text="the server's own",
        doc="for `--model ws://HOST:PORT`: a `harness.toml`-format file declaring the served policy's image convention "
            "and action space (`[env]`) and how the harness's observations map to the server's keys (`[served]`, "
            "[serving.md](serving.md)); without it the server's metadata says, else openpi's LIBERO example keys. Its "
            "content is part of the model fingerprint, its path is not")
    perturb: str | None = option(  # canonical "KIND[@KEY]:LEVEL,..." (envs.perturbations); None = nominal (level 0 too)
        None, "--perturb", {
            "run": "controlled perturbation of the scene (part of the protocol; docs/perturbations.md): camera, "
                   "lighting, texture, distractors, init-state, noise, language at level 0 (nominal) to 5; "
                   "camera@KEY / noise@KEY pick a camera, e.g. camera:3,lighting:1",
            "robustness": "comma-separated kinds (camera, lighting, texture, distractors, init-state, noise, language; "
                          "camera@KEY / noise@KEY for one camera)"},
        file=(str, list), metavar="KIND[@KEY]:LEVEL[,...]", sparse=True, default_text={"run": "none", "robustness": ""},
        convert=lambda v: perturb_text(parse_perturb(v)))
    # a run mixing task families (robosuite, LIBERO): {family: {env option: value}} where a family's own default
    # convention differs from `env` (harness.conventions.family_defaults); None when every task takes `env`
    family_env: Mapping[str, Mapping[str, Any]] | None = None
    # where each convention came from, per family: {family: {key: "flag" | "checkpoint" | "default:<family>"}};
    # recorded in the manifest ("conventions"), not part of the protocol's value (it does not change an episode)
    convention_sources: Mapping[str, Mapping[str, str]] | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "tasks", tuple(self.tasks))
        if not self.tasks:
            raise ValueError("no task given; pass --task NAME (see `octo-harness tasks`)")
        if not _is_int(self.episodes) or self.episodes < 1:
            raise ValueError(f"--episodes must be at least 1, got {self.episodes}")
        if self.max_steps is not None and (not _is_int(self.max_steps) or self.max_steps < 1):
            raise ValueError(f"--max-steps must be at least 1, got {self.max_steps}")
        if not _is_int(self.seed) or self.seed < 0:
            raise ValueError(f"--seed must be a non-negative integer, got {self.seed}")
        jobs = len(self.tasks) * self.episodes
        if jobs > MAX_JOBS:
            raise ValueError(f"--episodes {self.episodes} x {len(self.tasks)} task(s) is {jobs} episode jobs, more than "
                             f"one run holds ({MAX_JOBS}); split it into runs of at most {MAX_JOBS // len(self.tasks)} "
                             "episodes per task (--seed continues where the last one ended)")
        if self.seed + self.episodes - 1 > MAX_SEED:
            raise ValueError(f"--seed {self.seed} with --episodes {self.episodes} reaches seed "
                             f"{self.seed + self.episodes - 1}, outside the simulator's seed range 0..{MAX_SEED} "
                             f"(2**32 - 1, numpy's and robosuite's); choose --seed <= {MAX_SEED - self.episodes + 1}")
        if self.max_steps is not None and self.max_steps > MAX_STEPS:
            raise ValueError(f"--max-steps {self.max_steps} is more than an episode may run ({MAX_STEPS} control steps: "
                             "its arrays are held in memory until it ends); choose a smaller --max-steps")
        masked = [probe for probe in probes.active(self.policy) if probe.needs_masks]
        if masked and not self.env.masks:
            raise ValueError(masked[0].masks_error)
        object.__setattr__(self, "perturb", perturb_text(parse_perturb(self.perturb)))  # level 0 -> None: nominal

    def env_for(self, task: str) -> EnvOptions:
        """The env options of `task`: `env`, with its family's own defaults on top in a run that mixes families."""
        from harness.conventions import task_family

        changes = (self.family_env or {}).get(task_family(task))
        return self.env.replace(**changes) if changes else self.env

    def jobs(self) -> list[EpisodeJob]:
        """Episode jobs in run order: task by task, episode 0..episodes-1, seed + episode."""
        return [EpisodeJob(task=task, episode=k, seed=self.seed + k) for task in self.tasks for k in range(self.episodes)]

    def replace(self, **changes) -> "Protocol":
        return dataclasses.replace(self, **changes)

    def fingerprinted(self) -> "Protocol":
        """This protocol with `model_fingerprint` and `goal_fingerprint` computed from the files (stream-hashed)."""
        fp, _ = model_fingerprint(self.model, self.text_tokenizer, self.served_conventions)
        goals = goal_fingerprint(self.goal_images) if self.goal_images else None
        return self.replace(model_fingerprint=fp, goal_fingerprint=goals)

    def to_dict(self) -> dict:
        """Plain JSON data (what manifest.json holds under "protocol"); "execution" is a derived summary string."""
        return json_safe({
            "model": family_of(self.model).protocol_source(self.model),
            "model_fingerprint": self.model_fingerprint,
            "tasks": list(self.tasks),
            "episodes": self.episodes,
            "seed": self.seed,
            "max_steps": self.max_steps,
            "execution": self.policy.describe(),
            "instruction": self.instruction,
            "goal_images": self.goal_images,
            "goal_fingerprint": self.goal_fingerprint,
            "env": _plain(self.env),
            "policy": _plain(self.policy),
            "outputs": _plain(self.outputs),
            "harness_version": self.harness_version,
            # the options not listed above (text_tokenizer, perturb, ...): a sparse one only when set, so protocols
            # of the automatic choice or the nominal scene keep their hash and their run folder
            **{f.name: getattr(self, f.name) for f, o in options(Protocol) if o.hashed and f.name not in _LISTED
               and not (o.sparse and getattr(self, f.name) == f.default)},
            **({"family_env": {f: dict(v) for f, v in self.family_env.items()}} if self.family_env else {}),
        })

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "Protocol":
        """Inverse of `to_dict` (manifest.json -> Protocol); unknown keys raise."""
        data = dict(data)
        data.pop("execution", None)
        data.pop("convention_sources", None)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"protocol has unknown field(s) {unknown}; was it written by a newer octo-harness?")
        nested = {"env": EnvOptions, "policy": PolicyConfig, "outputs": OutputOptions}
        for name, kind in nested.items():
            if name in data and data[name] is not None:
                data[name] = build(kind, data[name])
        if "tasks" in data:
            data["tasks"] = tuple(data["tasks"])
        return cls(**data)

    def hash(self) -> str:
        return protocol_hash(self.to_dict())


_LISTED = ("model", "tasks", "episodes", "seed", "max_steps", "instruction", "goal_images")  # to_dict's fixed keys

CI_METHODS = ("wilson", "clopper-pearson")


@dataclass(frozen=True)
class RunStatistics:
    """How a run's derived files (results.json, summary.csv, statistics.csv) compute success intervals: recorded in
    the manifest ("statistics"), outside the protocol and its hash (the episodes are the same), so a resume, `run
    --resume` included, writes them as the run began."""

    ci_method: str = option(
        "wilson", "--ci-method", "confidence interval of success rates (95%%)", file=(str,), choices=CI_METHODS,
        hashed=False, doc="95% interval of success rates: Wilson score or the exact Clopper-Pearson; a resume (also "
        "`--resume`) writes the derived files with the recorded one; another method for a run that records one is "
        "refused (one line, exit 2) [wilson]")
    confidence: float = 0.95


def _retries(value) -> int:
    if not _is_int(value) or value < 0:
        raise ValueError(f"--retries must be an integer >= 0 (0: never retry), got {value!r}")
    return value


@dataclass(frozen=True)
class Recovery:
    """What a run does when it loses part of what runs it (a worker, a node, a policy replica, a LIBERO server):
    outside the protocol and its hash (the episodes are the same); what was retried is recorded in the manifest
    ("recovery") and in each retried episode's row (harness.run.executor.Retrying)."""

    retries: int = option(
        2, "--retries", "times a job that lost its worker, node, policy replica or LIBERO server runs again",
        type=int, file=(int,), hashed=False, sparse=True, convert=_retries, metavar="N",
        doc="times a job whose worker, node, policy replica or LIBERO server was lost runs again on another worker "
            "(episode failures never); a job still lost after N is an infrastructure failure, outside the "
            "statistics, that a resume runs again ([preemptible nodes](parallel.md#running-on-preemptible-nodes)) [2]")


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _plain(options) -> dict:
    return options.to_dict() if hasattr(options, "to_dict") else dataclasses.asdict(options)


def build(kind, data: Mapping[str, Any]):
    """A frozen options dataclass from plain data: its own `from_dict` when it has one, else its fields."""
    if hasattr(kind, "from_dict"):
        return kind.from_dict(data)
    names = {f.name for f in dataclasses.fields(kind)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown {kind.__name__} field(s) {unknown}; known: {sorted(names)}")
    return kind(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})




def diff(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """Dotted names of the fields whose values differ between two protocol dicts (sorted; derived "execution" skipped)."""
    a, b = flatten(json_safe(dict(old))), flatten(json_safe(dict(new)))
    return sorted(k for k in set(a) | set(b) if k != "execution" and a.get(k, _MISSING) != b.get(k, _MISSING))


_MISSING = object()


# ---------------------------------------------------------------------------------------------- fingerprints

def model_fingerprint(source: str, text_tokenizer: str | None = None,
                      served_conventions: str | None = None) -> tuple[str, dict]:
    """(fingerprint, details) of the policy `source` names, by its family (harness.policies): an Octo checkpoint's
    files (harness/policies/fingerprint.py), a policy server's declared identity (with its conventions file)."""
    return policy_fingerprint(source, **policy_options(text_tokenizer, served_conventions))


def policy_options(text_tokenizer: str | None = None, served_conventions: str | None = None) -> dict:
    """The options a policy family loads and fingerprints a source with (harness.policies.load_policy)."""
    return {"text_tokenizer": text_tokenizer, **({"served_conventions": served_conventions} if served_conventions else {})}


def load_protocol_policy(protocol: Protocol, source: str | None = None, text_tokenizer: str | None = None):
    """The policy a run of `protocol` stepped, loaded again (replay, view, sanity, a grid's camera keys): `source` in
    its place where given (a candidate, a served run's address, a checkpoint copied elsewhere), with the protocol's
    text tokenizer (or `text_tokenizer`) and its served conventions, the options the run itself loaded it with. One
    place, so no command reloads a run's policy with fewer of its options than the run used."""
    from harness.policies import load_policy

    tokenizer = text_tokenizer if text_tokenizer is not None else protocol.text_tokenizer
    return load_policy(source or protocol.model, **policy_options(tokenizer, protocol.served_conventions))


def goal_fingerprint(folder: str | Path) -> str | None:
    """sha256 over the goal images (<key>.png) in `folder`; None when it holds none."""
    folder = Path(folder)
    files = sorted(folder.glob("*.png")) if folder.is_dir() else []
    return files_fingerprint(folder, files)[0] if files else None


def protocol_from_manifest(manifest: dict, path: Path | str, **overrides):
    """The manifest's protocol as a `Protocol` (with `overrides` applied to its fields first); a value no Protocol
    accepts is a MalformedRunError naming the manifest, not a traceback."""
    protocol = manifest.get("protocol")
    if not protocol:
        raise MalformedRunError(f"{path} has no protocol (a run made before the run store); re-run it with this "
                                "octo-harness")
    check_protocol(protocol, path)
    try:
        return Protocol.from_dict({**protocol, **overrides})
    except (TypeError, ValueError, AttributeError, KeyError) as exc:
        message = str(exc.args[0] if isinstance(exc, KeyError) and exc.args else exc).splitlines()[0]
        raise MalformedRunError(f"{path}: its protocol is not valid ({message}); {FIX}") from None

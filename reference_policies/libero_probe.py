"""Grasp probe of a LIBERO-Object checkpoint (issue 46's table of levers): success, reach error and grasp rate on
the suite's stored initial states, the checkpoint run as the evaluation runs it.

    python -m reference_policies.libero_probe --model DIR [--states 0,1] [--workers 2] [--out FILE.json]
        (an --out file probed with the same checkpoint, states, tasks and step limit is reused, not probed again)
    python -m reference_policies.libero_probe --expert ...      (the state-based expert acts instead: the yardstick)
    python -m reference_policies.libero_probe --table LABEL=FILE.json ...   (the lever table, markdown, from --out files)

Per episode (stored state s of each task, the published loop: 10 settle steps, step limit 280, fast render, no
masks): success; the first step whose gripper command closes; there, the hand's horizontal and vertical distance
from the named object's grasp point (the expert's, reference_policies.libero_expert); whether the fingers held the
named object at any step (both pads touching), and lifted it (its bottom 3 cm above where it stood); the movable
object horizontally nearest the hand at the first close (which one the grasp went for); the object picked at the end
(`episode_outcome`); the longest stall after the first close (gripper commanded open, hand barely commanded:
harness.analysis.grounding.longest_stall) and where the hand was in its middle. The summary gives
the success rate, the median reach error at the first close, the grasp rate (named object held at some step), the
lift rate, the rate of ending with another object and the rate of stalling open for 100 steps or more. Episodes
run in spawned processes, one job a task, so the numbers do not depend on the workers.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from harness.analysis.grounding import CLOSED_BELOW, STALL_STEPS, longest_stall
from harness.files import atomic_write_json, json_safe
from harness.options import option
from reference_policies.libero_demos import LIBERO_OBJECT_TASKS
from reference_policies.libero_expert import with_radii
from reference_policies.options import Workers, add_options, parse, values

log = logging.getLogger(__name__)

MAX_STEPS = 280  # LIBERO-Object's published step limit
LIFTED = 0.03  # m: the named object's bottom this far above where it stood counts as lifted


def _actor(model_dir: str | None, task: str, max_steps: int, radii: str = "", language: str = ""):
    """(env, target, instruction or None, reset(info, state), act(obs) -> action): the checkpoint as evaluated, or
    the state-based expert (with `radii`, reference_policies.libero_expert.with_radii, in place of its own). With
    `language="swap"` the instruction and the target are those of the scene's swap (reference_policies.libero_eval:
    the next task whose named object the scene holds); else the task's own (instruction None)."""
    from envs.libero_tasks import get_libero_task
    from reference_policies.libero_demos import evaluation_swap
    from reference_policies.libero_expert import LiberoObjectLabeller

    if model_dir is None:
        import envs

        env = envs.make(task, cameras={}, fast_render=True, masks=False, action_space="libero",
                        max_episode_steps=max_steps)
    else:
        from reference_policies.dagger import policy_in_env

        env, policy = policy_in_env(model_dir, task, max_steps)
    named, instruction = get_libero_task(task), None
    if language == "swap":
        other = evaluation_swap(task, env.description.get("movable", env.description["objects"]))
        if other is None:
            env.close()
            raise ValueError(f"{task}: its scene holds no other task's named object, so it has no swap")
        named = get_libero_task(other)
        instruction = named.instruction
    target = named.targets[0]
    if model_dir is None:
        labeller = LiberoObjectLabeller(target, config=with_radii(radii))
        return env, target, instruction, lambda info, state: None, lambda obs: labeller.act(env, obs)
    return env, target, instruction, \
        lambda info, state: policy.reset(instruction or info.get("instruction", ""), seed=state), \
        lambda obs: policy.step(obs).action


def _probe_job(args: tuple) -> list[dict]:
    """Spawned worker: one task's episodes from stored states `states` -> a row each."""
    from reference_policies.libero_demos import placed_alone
    from reference_policies.libero_expert import LiberoExpertConfig, grasp_geometry

    model_dir, task, states, max_steps, radii, language = args
    env, target, instruction, reset, act = _actor(model_dir, task, max_steps, radii, language)
    rows = []
    movable = [n for n in env.description.get("movable", env.description["objects"]) if n != "basket_1"]
    from reference_policies.libero_expert import LiberoObjectLabeller

    judge = LiberoObjectLabeller(target)  # what the demonstrator (its own radii) would do in each state reached
    try:
        for state in states:
            obs, info = env.reset(seed=state)
            reset(info, state)
            row = {"task": task, "state": state, "target": target, "first_close": None, "reach_xy_cm": None,
                   "reach_z_cm": None, "held_named": False, "lifted_named": False, "success": False, "steps": 0}
            if instruction is not None:
                row["instruction"] = instruction
            floor = env.object_poses()[target]["low"][2]
            executed, where = [], []  # each step's action; after it, the hand, the named object's box, the expert's label
            for step in range(max_steps):
                action = np.asarray(act(obs), np.float64)
                executed.append(action)
                if row["first_close"] is None and action[-1] < 0.5:  # the "libero" gripper: 1 open, 0 closed
                    poses = env.object_poses()
                    grasp = grasp_geometry(poses, target, "basket_1", LiberoExpertConfig())["grasp"]
                    hand = np.asarray(obs["proprio"][:3], np.float64)
                    row.update(first_close=step, reach_xy_cm=round(float(np.linalg.norm(hand[:2] - grasp[:2])) * 100, 2),
                               reach_z_cm=round(float(hand[2] - grasp[2]) * 100, 2),
                               nearest_at_close=_nearest(poses, hand, movable))
                obs, _, terminated, truncated, info = env.step(action)
                poses, held = env.object_poses(), bool(env.grasping(target))  # read once: the judge reuses them
                box = poses[target]
                where.append((np.asarray(obs["proprio"][:3], np.float64), box["low"], box["high"],
                              judge.act_on(obs, poses, held)))
                row["held_named"] = row["held_named"] or held
                row["lifted_named"] = row["lifted_named"] or bool(box["low"][2] > floor + LIFTED)
                row["steps"] = step + 1
                # a swap succeeds when the named object, alone, is in the basket (the scene's own predicate ends it)
                row["success"] = bool(info["success"]) if instruction is None else placed_alone(env, target)
                if row["success"] or terminated or truncated:
                    break
            row["picked"] = env.episode_outcome()["picked_object"]
            row.update(stall_measures(executed, where))
            rows.append(row)
    finally:
        env.close()
    return rows


def stall_measures(executed: list, where: list) -> dict:
    """The episode's longest stall (harness.analysis.grounding.longest_stall: gripper open, hand barely commanded,
    after the first close) in steps, and in its middle step: where the hand was, horizontally from the named object's
    box centre and vertically above the box's top, in cm, and whether the demonstrator's label there closes the
    gripper (None without a stall). `where`: per step, (hand, box low, box high, the demonstrator's action) after it."""
    start, length = longest_stall(np.asarray(executed, np.float64).reshape(len(executed), -1))
    out = {"stall_steps": length, "stall_xy_cm": None, "stall_above_top_cm": None, "stall_expert_closes": None}
    if length:
        hand, low, high, label = where[start + length // 2]
        centre = (np.asarray(low, np.float64) + np.asarray(high, np.float64)) / 2
        out.update(stall_xy_cm=round(float(np.linalg.norm(hand[:2] - centre[:2])) * 100, 2),
                   stall_above_top_cm=round(float(hand[2] - high[2]) * 100, 2),
                   stall_expert_closes=bool(label[-1] < CLOSED_BELOW))
    return out


def run_stalls(run_dir) -> list[tuple[str, int, int, int]]:
    """(task, finished episodes, failed, failed that stalled open STALL_STEPS+ steps) per task of a LIBERO run
    folder, read through harness.analysis.runs (an untrusted folder: a file that does not match its row is one
    line, exit 2). Refuses a run whose actions are not the "libero" action space (another gripper convention)."""
    from harness.analysis.runs import MalformedRunError, load_run
    from harness.bounded import open_npz

    record = load_run(run_dir)
    env = record.manifest.get("protocol", {}).get("env", {}) if isinstance(record.manifest.get("protocol"), dict) else {}
    if not isinstance(env, dict) or env.get("action_space") != "libero":
        raise MalformedRunError(f"{record.path}: not a run in the libero action space (its gripper: 1 open, 0 closed); "
                                "--stalls reads LIBERO runs such as the reference's published evaluation")
    rows = []
    for task in record.tasks:
        episodes = [e for e in record.task_episodes(task) if e.ok]
        failed = [e for e in episodes if not e.success]
        stalled = 0
        for e in failed:
            try:
                with open_npz(e.directory / "actions.npz") as z:
                    executed = np.asarray(z["executed"], np.float64)
            except (OSError, ValueError, KeyError) as exc:
                raise MalformedRunError(f"{e.directory / 'actions.npz'}: unreadable ({str(exc).splitlines()[0]})") from None
            if executed.ndim != 2 or executed.shape[1] != 7:
                raise MalformedRunError(f"{e.directory / 'actions.npz'}: 'executed' is {executed.shape}, not steps x 7")
            stalled += longest_stall(executed)[1] >= STALL_STEPS
        rows.append((task, len(episodes), len(failed), stalled))
    return rows


def stall_table(rows: list[tuple[str, int, int, int]]) -> str:
    lines = ["| task | episodes | failed | failed, stalled open " + f"{STALL_STEPS}+ steps |", "|---|---|---|---|"]
    lines += [f"| {task} | {n} | {failed} | {stalled} |" for task, n, failed, stalled in rows]
    total = [sum(r[i] for r in rows) for i in (1, 2, 3)]
    lines.append(f"| all | {total[0]} | {total[1]} | {total[2]} |")
    return "\n".join(lines)


def _nearest(poses: dict, hand: np.ndarray, movable: list[str]) -> str | None:
    """The movable object whose box centre is horizontally nearest the hand (which one the grasp went for)."""
    distance = {n: float(np.linalg.norm(hand[:2] - (poses[n]["low"][:2] + poses[n]["high"][:2]) / 2))
                for n in movable if n in poses}
    return min(distance, key=distance.get) if distance else None


def summarise(rows: list[dict]) -> dict:
    """Rates over the episodes and the median reach error at the first close (over episodes that closed)."""
    n = len(rows)
    reach = [r["reach_xy_cm"] for r in rows if r["reach_xy_cm"] is not None]
    nearest = [r for r in rows if r.get("nearest_at_close") is not None]
    picked = [r for r in rows if r.get("picked") is not None]
    per_task: dict[str, int] = {}
    for r in rows:
        per_task[r["task"]] = per_task.get(r["task"], 0) + int(r["success"])
    return {"episodes": n, "successes": sum(r["success"] for r in rows),
            "success_rate": sum(r["success"] for r in rows) / n if n else None,
            "closed": len(reach), "median_reach_xy_cm": float(np.median(reach)) if reach else None,
            "median_first_close": float(np.median([r["first_close"] for r in rows if r["first_close"] is not None]))
            if reach else None,
            "grasp_rate": sum(r["held_named"] for r in rows) / n if n else None,
            "lift_rate": sum(r["lifted_named"] for r in rows) / n if n else None,
            "other_object_rate": sum(r["picked"] not in (None, r["target"]) for r in rows) / n if n else None,
            # of the episodes that closed: the first close nearest the named object (None in results made before)
            "nearest_named_rate": (sum(r["nearest_at_close"] == r["target"] for r in nearest) / len(nearest)
                                   if nearest else None),
            # of the episodes that ended with an object in the basket or the hand: it was the named one
            "picked_named_rate": sum(r["picked"] == r["target"] for r in picked) / len(picked) if picked else None,
            "picked": len(picked), "successes_per_task": per_task, **_stalls(rows)}


def _stalls(rows: list[dict]) -> dict:
    """How many episodes stalled open for STALL_STEPS or more, and where the hand was then (medians, cm); None
    for results made before the stall was measured."""
    if not rows or any("stall_steps" not in r for r in rows):
        return {"stalled": None, "stall_rate": None, "stalled_expert_closes": None, "median_stall_xy_cm": None,
                "median_stall_above_top_cm": None}
    stalled = [r for r in rows if r["stall_steps"] >= STALL_STEPS]
    judged = [r for r in stalled if r.get("stall_expert_closes") is not None]
    return {"stalled": len(stalled), "stall_rate": len(stalled) / len(rows),
            # of the stalled episodes: where the demonstrator, in the stall's middle, would close the gripper
            "stalled_expert_closes": sum(r["stall_expert_closes"] for r in judged) if judged else None,
            "median_stall_xy_cm": float(np.median([r["stall_xy_cm"] for r in stalled])) if stalled else None,
            "median_stall_above_top_cm": float(np.median([r["stall_above_top_cm"] for r in stalled])) if stalled else None}


def probe(model_dir: str | None, states: list[int], tasks: tuple[str, ...] = LIBERO_OBJECT_TASKS, workers: int = 2,
          max_steps: int = MAX_STEPS, radii: str = "", language: str = "") -> dict:
    from reference_policies.demos import run_jobs

    start = time.perf_counter()
    jobs = [(model_dir, task, states, max_steps, radii, language) for task in tasks]
    rows = [row for part in run_jobs(_probe_job, jobs, workers) for row in part]
    return {"model": model_dir or "expert", "states": states, "max_steps": max_steps, "language": language or "own",
            "summary": summarise(rows), "episodes": rows, "seconds": round(time.perf_counter() - start, 1)}


PROBE_VERSION = 2  # raise when what a probe measures changes: older result files are then probed again


def probe_key(model_dir: str | None, states: list[int], tasks: tuple[str, ...], max_steps: int, radii: str = "",
              language: str = "") -> dict:
    """What a probe result depends on: the checkpoint's fingerprint (or the expert and the radii it was given),
    states, tasks, step limit, and the instructions when not the tasks' own ("swap")."""
    from reference_policies.dagger import checkpoint_fingerprint
    from reference_policies.libero_expert import RADII, LiberoExpertConfig

    given, default = with_radii(radii), LiberoExpertConfig()
    expert = "expert" + "".join(f" {n}={getattr(given, n)}" for n in RADII if getattr(given, n) != getattr(default, n))
    return {"version": PROBE_VERSION, "checkpoint": expert if model_dir is None else checkpoint_fingerprint(model_dir),
            "states": list(states), "tasks": list(tasks), "max_steps": max_steps, **({"language": language} if language else {})}


def _finished(path: str, key: dict) -> dict | None:
    """The probe result in `path` when it was made with exactly `key`, else None (missing, foreign, torn, huge)."""
    file = Path(path)
    try:
        if not file.is_file() or file.stat().st_size > 64 << 20:
            return None
        result = json.loads(file.read_text())
        return result if isinstance(result, dict) and result.get("key") == key and "summary" in result else None
    except (OSError, ValueError, UnicodeDecodeError):
        return None


TABLE_COLUMNS = ("lever", "episodes", "success", "median reach at first close (cm)", "first close (step)",
                 "closed nearest the named object", "grasp rate", "lift rate", "ended with another object",
                 "picked the named object (of those picked)", f"stalled open {STALL_STEPS}+ steps")


def _rate(value) -> str:
    return "-" if value is None else f"{100 * value:.0f}%"


def _picked(summary: dict) -> str:
    if summary.get("picked_named_rate") is None:  # none picked, or a result made before the column
        return "-" if "picked" not in summary else "0 picked"
    return f"{_rate(summary['picked_named_rate'])} of {summary['picked']}"


def _stalled(summary: dict) -> str:
    if summary.get("stall_rate") is None:  # a result made before the stall was measured
        return "-"
    if not summary["stalled"]:
        return "0%"
    closes = summary.get("stalled_expert_closes")
    judged = "" if closes is None else f"; the demonstrator would close in {closes} of {summary['stalled']}"
    return (f"{_rate(summary['stall_rate'])} (hand {summary['median_stall_xy_cm']:.1f} cm off the object, "
            f"{summary['median_stall_above_top_cm']:.1f} cm above its top{judged})")


def lever_table(entries: list[tuple[str, dict]]) -> str:
    """Markdown table of probe results, one row per (label, probe result) in the given order."""
    lines = ["| " + " | ".join(TABLE_COLUMNS) + " |", "|" + "---|" * len(TABLE_COLUMNS)]
    for label, result in entries:
        s = result["summary"]
        reach = "-" if s["median_reach_xy_cm"] is None else f"{s['median_reach_xy_cm']:.1f} ({s['closed']} closed)"
        first = "-" if s["median_first_close"] is None else f"{s['median_first_close']:.0f}"
        lines.append("| " + " | ".join([label, str(s["episodes"]), f"{s['successes']}/{s['episodes']}", reach, first,
                                        _rate(s.get("nearest_named_rate")), _rate(s["grasp_rate"]), _rate(s["lift_rate"]),
                                        _rate(s["other_object_rate"]), _picked(s), _stalled(s)]) + " |")
    return "\n".join(lines)


def _load_table_entry(spec: str, parser: argparse.ArgumentParser) -> tuple[str, dict]:
    label, sep, path = spec.partition("=")
    if not sep or not label or not path:
        parser.error(f"--table {spec!r}: give LABEL=FILE.json (a file --out wrote)")
    file = Path(path)
    if not file.is_file() or file.stat().st_size > 64 << 20:
        parser.error(f"--table {spec!r}: {path} is not a probe result under 64 MiB (write one with --out)")
    try:
        result = json.loads(file.read_text())
        summary = result["summary"]
        for key in ("episodes", "successes", "median_reach_xy_cm", "closed", "median_first_close", "grasp_rate",
                    "lift_rate", "other_object_rate"):
            summary[key]
        if ("picked" not in summary or "stall_rate" not in summary) and isinstance(result.get("episodes"), list):
            # a result made before a column was added: summarised again from its rows, so every column is filled
            result = {**result, "summary": summarise(result["episodes"])}
    except (ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError):
        parser.error(f"--table {spec!r}: {path} is not a probe result (write one with --out)")
    return label, result


@dataclass(frozen=True)
class ProbeOptions:
    """The probe's options: who acts (one of the first four), then where and how long; the processes are `Workers`'."""
    model: str | None = option(None, "--model", "checkpoint folder (with its harness.toml)")
    expert: bool = option(False, "--expert", "the state-based expert acts (the yardstick)", action="store_true")
    table: list | None = option(None, "--table", "print the lever table (markdown) of probe results that --out wrote, "
                                "in this order", metavar="LABEL=FILE.json")
    stalls: str | None = option(None, "--stalls", "print, per task of a LIBERO run folder (the libero action space), "
                                f"how many failed episodes stalled open {STALL_STEPS}+ steps, from their actions.npz "
                                "(markdown)", metavar="RUN_DIR")
    expert_radii: str = option("", "--expert-radii", "with --expert: its radii (centred, at_grasp, grasp_height), e.g. "
                               "grasp_height=0.004", metavar="NAME=METRES,...", default_text="LiberoExpertConfig's")
    language: str = option("own", "--language", "swap: each scene is told the next task's instruction whose named "
                           "object it holds (reference_policies.libero_eval swaps); success is that object, alone, in "
                           "the basket", choices=("own", "swap"))
    states: str = option("0,1", "--states", "stored initial states of every task")
    tasks: str = option("", "--tasks", "LIBERO-Object tasks", default_text="all ten")
    max_steps: int = option(MAX_STEPS, "--max-steps", "step limit of an episode (LIBERO-Object's published one)",
                            type=int)
    out: str | None = option(None, "--out", "write the rows and the summary here (JSON)", default_text="printed only")


WHO = ("model", "expert", "table", "stalls")  # exactly one of them is given


def command_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m reference_policies.libero_probe", description=__doc__.splitlines()[0])
    add_options(parser.add_mutually_exclusive_group(required=True), (ProbeOptions,), only=WHO,
                overrides={"table": {"nargs": "+"}})
    add_options(parser, (ProbeOptions,), only=[f.name for f in fields(ProbeOptions) if f.name not in WHO])
    add_options(parser, (Workers,))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = command_parser()
    given, options = parse(parser, ProbeOptions, argv)
    try:
        workers = Workers(**values(Workers, given))
    except ValueError as e:
        parser.error(str(e))
    args = argparse.Namespace(**asdict(options), **asdict(workers))
    args.tasks = args.tasks or ",".join(LIBERO_OBJECT_TASKS)
    if args.table:
        print(lever_table([_load_table_entry(spec, parser) for spec in args.table]))
        return 0
    if args.stalls:
        from harness.analysis.runs import MalformedRunError, NotARunError

        try:
            print(stall_table(run_stalls(args.stalls)))
        except (NotARunError, MalformedRunError) as exc:
            parser.error(f"--stalls {args.stalls}: {str(exc).splitlines()[0]}")
        return 0
    try:
        states = [int(s) for s in args.states.split(",")]
    except ValueError:
        parser.error(f"--states {args.states!r}: comma-separated stored-state indices, e.g. 0,1")
    if args.model is not None and not (Path(args.model) / "config.json").is_file():
        parser.error(f"--model {args.model}: no checkpoint there (a folder with config.json)")
    if args.expert_radii:
        if not args.expert:
            parser.error("--expert-radii sets the expert's radii: give it with --expert")
        try:
            with_radii(args.expert_radii, option="--expert-radii")
        except ValueError as e:
            parser.error(str(e))
    if not 0 < args.max_steps <= 10_000 or not all(0 <= s < 50 for s in states):
        parser.error("--max-steps 1..10000; --states within LIBERO's 50 stored states (0..49)")
    if args.out:
        try:  # a folder that cannot hold the result is told before the episodes run, not after
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            parser.error(f"--out {args.out}: cannot write there ({exc.strerror}); give a writable path")
        if Path(args.out).is_dir():
            parser.error(f"--out {args.out} is a folder; give a file name such as probe.json")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    tasks = tuple(t.strip() for t in args.tasks.split(","))
    if not tasks or any(t not in LIBERO_OBJECT_TASKS for t in tasks):
        parser.error(f"--tasks {args.tasks!r}: LIBERO-Object tasks, e.g. libero_object/0,libero_object/6 (the probe "
                     "reads their basket and named objects)")
    language = "" if args.language == "own" else args.language
    key = probe_key(args.model, states, tasks, args.max_steps, args.expert_radii, language)
    done = _finished(args.out, key) if args.out else None
    if done is not None:
        log.info("reusing %s: the same checkpoint, states, tasks and step limit were probed there", args.out)
        result = done
    else:
        result = {"key": key, **probe(args.model, states, tasks, args.workers, args.max_steps, args.expert_radii,
                                      language)}
    if args.out and done is None:
        atomic_write_json(args.out, result)
    print(json.dumps(json_safe(result["summary"])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The hostile-file corpus (issue 44): each class of damaged or hostile input, made from one small real run folder,
with the command that reads it and what that command must answer (exit code, a phrase of its one line).

    PYTHONPATH=. .venv/bin/python tests/runfolder/hostile_corpus.py RUN_DIR OUT_DIR MODEL_DIR  # writes and lists every case

`make_cases(run, out, model)` copies `run` (a finished run of the tiny model) once per case into `out/<case>` and
edits the copy; it returns the `Case`s. tests/runfolder/test_hostile_inputs.py runs each case's command in a
subprocess with a timeout and a memory cap and checks the answer; docs/run-integrity.md states the limits.

Classes: deep nesting (manifest.json, a results.jsonl row, episode.json, robustness.json, a checkpoint's
config.json, a protocol file), sparse giants (manifest.json, results.jsonl), array bombs (a member longer than the
row's steps, one that expands to hundreds of MB, one whose layers differ from the manifest's, one holding pickled
objects, one whose header disagrees with its zip entry), edited manifests (protocol.seed, a job's seed, max_steps
with the stored hash kept, protocol + hash + jobs edited together, manifest.json deleted, arrays deleted under rows
without digests), not regular files (a FIFO or a device as results.jsonl, a FIFO as manifest.json or as a protocol
file; a device needs a user who may make one), the viewer (ports out of range, a port in use, spawn without a
display, a foreign episode.rrd), small ones (an empty --perturb, --controls-every 0, a huge bad value, a checkpoint claiming 10000 layers).
Full disks, SIGINT while loading and resume over a plain file need a mount, a process or a long run: they are
tests of their own in test_hostile_inputs.py.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import sys
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

DEEP = 100_000  # nesting levels of the deep documents
GIANT = 20 << 30  # bytes of the sparse giants (20 GB; sparse: no disk used)
BOMB_SHAPE = (2, 4, 20_000_000)  # float32: 640 MB from a zip of about 3 MB (zeros)


@dataclass
class Case:
    name: str
    cls: str  # the class of the issue it belongs to
    argv: list[str]  # octo-harness arguments
    code: int  # the documented exit code
    says: str  # a phrase the one line (stderr for errors, stdout for 0) must hold
    env: dict = field(default_factory=dict)  # extra environment


def _copy(run: Path, out: Path, name: str) -> Path:
    dest = out / name
    shutil.copytree(run, dest)
    manifest = json.loads((dest / "manifest.json").read_text())
    manifest["run"] = name
    (dest / "manifest.json").write_text(json.dumps(manifest))
    return dest


def _manifest(run: Path) -> dict:
    return json.loads((run / "manifest.json").read_text())


def _write_manifest(run: Path, manifest: dict) -> None:
    (run / "manifest.json").write_text(json.dumps(manifest))


def _rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "results.jsonl").read_text().splitlines() if line.strip()]


def _write_rows(run: Path, rows: list[dict]) -> None:
    (run / "results.jsonl").write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in rows))


def _redigest(run: Path) -> None:
    """Record the files now in each episode folder in its row, as if the run had written them (a careful forger)."""
    from harness.runfolder.integrity import data_digests

    rows = _rows(run)
    for row in rows:
        if row.get("files"):
            row["files"] = data_digests(run / row["directory"], list(row["files"]))
    _write_rows(run, rows)


def _rehash(run: Path) -> None:
    from harness.runfolder.schema import protocol_hash

    manifest = _manifest(run)
    manifest["protocol_hash"] = protocol_hash(manifest["protocol"])
    _write_manifest(run, manifest)


def _deep(path: Path, wrap: str = "{{\"deep\": {}}}") -> None:
    path.write_text(wrap.format("[" * DEEP + "]" * DEEP))


def _sparse(path: Path) -> None:
    with open(path, "r+b" if path.exists() else "wb") as f:
        f.truncate(GIANT)


def _special(path: Path, device: bool = False) -> bool:
    """Put a FIFO (or a character device: a copy of /dev/null) in `path`'s place; False when this user may not make
    a device."""
    path.unlink(missing_ok=True)
    if not device:
        os.mkfifo(path)
        return True
    try:
        os.mknod(path, 0o600 | stat.S_IFCHR, os.makedev(1, 3))
    except PermissionError:
        return False
    return True


def _npz_replace(path: Path, name: str, array_header: dict | None = None, array: np.ndarray | None = None,
                 zeros_bytes: int | None = None, pickled: bool = False) -> None:
    """Rewrite one member of a .npz: a given array, or a header plus `zeros_bytes` of zeros streamed through deflate
    (the bomb: nothing that large is ever in memory)."""
    from numpy.lib import format as npformat

    with np.load(path) as z:
        keep = {k: z[k] for k in z.files if k != name}
    tmp = path.with_suffix(".tmp.npz")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for key, value in keep.items():
            with archive.open(f"{key}.npy", "w", force_zip64=True) as f:
                npformat.write_array(f, value)
        with archive.open(f"{name}.npy", "w", force_zip64=True) as f:
            if pickled:
                npformat.write_array(f, np.array([{"a": 1}], dtype=object), allow_pickle=True)
            elif array is not None:
                npformat.write_array(f, array)
            else:
                npformat.write_array_header_1_0(f, array_header)
                block = bytes(1 << 24)
                left = zeros_bytes
                while left > 0:
                    f.write(block[:min(left, len(block))])
                    left -= len(block)
    os.replace(tmp, path)


def make_cases(run: Path, out: Path, model: str, rrd: Path | None = None) -> list[Case]:
    """Every case of the corpus as a folder under `out` (made from copies of `run`); `model`: the run's checkpoint
    folder (copied for the checkpoint cases); `rrd`: another recording to plant as a foreign episode.rrd."""
    run, out = Path(run), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    good = _copy(run, out, "good")
    ep = "Lift/episode_0"
    cases: list[Case] = []

    def compare(name: str, cls: str, code: int, says: str) -> None:
        cases.append(Case(name, cls, ["compare", str(good), str(out / name), "--no-frames", "--out",
                                      str(out / f"{name}.cmp")], code, says))

    # ---- deep nesting ----------------------------------------------------------------------------------------
    bad = _copy(run, out, "deep_manifest")
    _deep(bad / "manifest.json")
    compare("deep_manifest", "deep nesting", 2, "levels deep")
    bad = _copy(run, out, "deep_row")
    (bad / "results.jsonl").write_text((bad / "results.jsonl").read_text() + '{"deep": ' + "[" * DEEP + "]" * DEEP + "}\n")
    cases.append(Case("deep_row", "deep nesting", ["report", str(bad), "--out", str(out / "deep_row.report")], 2,
                      "levels deep"))
    bad = _copy(run, out, "deep_episode_json")
    _deep(bad / ep / "episode.json")
    cases.append(Case("deep_episode_json", "deep nesting", ["view", str(bad), "--no-simulate", "--save",
                                                            str(out / "deep_episode_json.rrd")], 2, "levels deep"))
    for side in ("a", "b"):
        grid = out / f"deep_grid_{side}"
        grid.mkdir()
        _deep(grid / "robustness.json")
    cases.append(Case("deep_grid", "deep nesting", ["compare", str(out / "deep_grid_a"), str(out / "deep_grid_b"),
                                                    "--no-frames"], 2, "levels deep"))
    ckpt = out / "deep_config"
    shutil.copytree(model, ckpt)
    config = json.loads((ckpt / "config.json").read_text())
    config["deep"] = "PLACEHOLDER"
    (ckpt / "config.json").write_text(json.dumps(config).replace('"PLACEHOLDER"', "[" * DEEP + "]" * DEEP))
    cases.append(Case("deep_config", "deep nesting", ["run", "--model", str(ckpt), "--task", "Lift", "--max-steps", "2",
                                                      "--out", str(out / "deep_config.out")], 2, "levels deep"))
    toml = out / "deep_protocol.toml"
    toml.write_text("task = " + "[" * DEEP + '"Lift"' + "]" * DEEP + "\n")
    cases.append(Case("deep_protocol", "deep nesting", ["run", "--protocol", str(toml), "--out",
                                                        str(out / "deep_protocol.out")], 2, "levels deep"))

    # ---- sparse giants ---------------------------------------------------------------------------------------
    bad = _copy(run, out, "giant_manifest")
    _sparse(bad / "manifest.json")
    compare("giant_manifest", "sparse giant", 2, "MiB a JSON file may hold")
    bad = _copy(run, out, "giant_results")
    _sparse(bad / "results.jsonl")
    cases.append(Case("giant_results", "sparse giant", ["report", str(bad), "--out", str(out / "giant_results.report")],
                      2, "MiB a JSON-lines file may hold"))

    # ---- array bombs (digests recorded, as a careful forger would) -------------------------------------------
    bad = _copy(run, out, "bomb_actions")
    _npz_replace(bad / ep / "actions.npz", "predicted",
                 {"descr": "<f4", "fortran_order": False, "shape": BOMB_SHAPE}, zeros_bytes=int(np.prod(BOMB_SHAPE)) * 4)
    _redigest(bad)
    compare("bomb_actions", "zip bomb", 2, "bytes per step")
    bad = _copy(run, out, "long_actions")
    with np.load(bad / ep / "actions.npz") as z:
        executed = z["executed"]
    _npz_replace(bad / ep / "actions.npz", "executed", array=np.repeat(executed, 5000, axis=0))
    _redigest(bad)
    compare("long_actions", "zip bomb", 2, "but its row records 2")
    bad = _copy(run, out, "layers_attention")
    with np.load(bad / ep / "attention.npz") as z:
        attention = z["readout_attention"]
    _npz_replace(bad / ep / "attention.npz", "readout_attention", array=np.repeat(attention, 3, axis=1))
    _redigest(bad)
    compare("layers_attention", "zip bomb", 2, "the run's manifest implies")
    bad = _copy(run, out, "pickled_actions")
    _npz_replace(bad / ep / "actions.npz", "reward", pickled=True)
    _redigest(bad)
    compare("pickled_actions", "zip bomb", 2, "holds Python objects")
    bad = _copy(run, out, "lying_header")
    _npz_replace(bad / ep / "actions.npz", "reward", {"descr": "<f4", "fortran_order": False, "shape": (2, 1 << 20)},
                 zeros_bytes=8)
    _redigest(bad)
    compare("lying_header", "zip bomb", 2, "its zip entry holds")

    # ---- edited manifests ------------------------------------------------------------------------------------
    bad = _copy(run, out, "edited_seed")
    manifest = _manifest(bad)
    manifest["protocol"]["seed"] = 7
    _write_manifest(bad, manifest)
    compare("edited_seed", "edited manifest", 2, "protocol.seed")
    cases.append(Case("edited_seed_resume", "edited manifest", ["run", "--resume", str(bad)], 2, "protocol.seed"))
    cases.append(Case("edited_seed_report", "edited manifest", ["report", str(bad), "--out",
                                                                str(out / "edited_seed.report")], 2, "protocol.seed"))
    cases.append(Case("edited_seed_replay", "edited manifest", ["replay", str(bad), "--out",
                                                                str(out / "edited_seed.replay")], 2, "protocol.seed"))
    cases.append(Case("edited_seed_view", "edited manifest", ["view", str(bad), "--no-simulate", "--save",
                                                              str(out / "edited_seed.rrd")], 2, "protocol.seed"))
    cases.append(Case("edited_seed_regress", "edited manifest", ["regress", "--baseline", str(bad), "--model", model,
                                                                 "--out", str(out / "edited_seed.regress")], 2,
                      "protocol.seed"))
    bad = _copy(run, out, "edited_job_seed")
    manifest = _manifest(bad)
    manifest["jobs"][0][2] = 9
    _write_manifest(bad, manifest)
    compare("edited_job_seed", "edited manifest", 2, "jobs[0]")
    bad = _copy(run, out, "edited_max_steps")
    manifest = _manifest(bad)
    manifest["protocol"]["max_steps"] = 50
    _write_manifest(bad, manifest)
    (bad / "results.json").unlink()  # no derived copy to name the field from: the hash alone refuses it
    compare("edited_max_steps", "edited manifest", 2, "does not match its protocol_hash")
    bad = _copy(run, out, "edited_all")
    manifest = _manifest(bad)
    manifest["protocol"]["seed"] = 7
    manifest["jobs"] = [[t, k, 7 + k] for t, k, _ in manifest["jobs"]]
    _write_manifest(bad, manifest)
    _rehash(bad)
    compare("edited_all", "edited manifest", 2, "is not its job's seed")
    bad = _copy(run, out, "no_manifest")
    (bad / "manifest.json").unlink()
    compare("no_manifest", "edited manifest", 2, "manifest.json is missing")
    bad = _copy(run, out, "legacy_no_arrays")
    rows = _rows(bad)
    for row in rows:
        row.pop("files", None)
    _write_rows(bad, rows)
    for name in ("actions.npz", "attention.npz", "inputs.npz"):
        (bad / ep / name).unlink()
    compare("legacy_no_arrays", "edited manifest", 2, "is missing")

    # ---- not regular files (a FIFO is never opened: a command reading it would block) ---------------------------
    bad = _copy(run, out, "fifo_rows")
    _special(bad / "results.jsonl")
    cases.append(Case("fifo_rows", "not a regular file", ["report", str(bad), "--out", str(out / "fifo_rows.report")],
                      2, "results.jsonl is not a regular file (it is a FIFO)"))
    bad = _copy(run, out, "device_rows")
    if _special(bad / "results.jsonl", device=True):
        cases.append(Case("device_rows", "not a regular file", ["report", str(bad), "--out",
                                                                 str(out / "device_rows.report")], 2,
                          "results.jsonl is not a regular file (it is a character device)"))
    bad = _copy(run, out, "fifo_manifest")
    _special(bad / "manifest.json")
    compare("fifo_manifest", "not a regular file", 2, "manifest.json is not a regular file (it is a FIFO)")
    fifo = out / "fifo_protocol.toml"
    _special(fifo)
    cases.append(Case("fifo_protocol", "not a regular file", ["run", "--protocol", str(fifo), "--out",
                                                              str(out / "fifo_protocol.out")], 2,
                      "is not a regular file (it is a FIFO)"))

    # ---- the viewer --------------------------------------------------------------------------------------------
    cases.append(Case("viewer_port_range", "viewer", ["run", "--model", model, "--task", "Lift", "--rerun", "spawn",
                                                      "--viewer-port", "99999"], 2, "port number 1-65535"))
    cases.append(Case("web_port_negative", "viewer", ["view", str(good), "--serve", "--web-port", "-1"], 2,
                      "port number 1-65535"))
    no_display = {"DISPLAY": "", "WAYLAND_DISPLAY": ""}
    cases.append(Case("spawn_no_display_run", "viewer", ["run", "--model", model, "--task", "Lift", "--max-steps", "2",
                                                         "--rerun", "spawn", "--out", str(out / "spawn.out")], 2,
                      "no display here for a viewer window", no_display))
    cases.append(Case("spawn_no_display_view", "viewer", ["view", str(good)], 2, "no display here for a viewer window",
                      no_display))
    if rrd is not None:
        bad = _copy(run, out, "foreign_rrd")
        shutil.copyfile(rrd, bad / ep / "episode.rrd")
        cases.append(Case("foreign_rrd", "viewer", ["view", str(bad), "--no-simulate", "--save",
                                                    str(out / "foreign_rrd.rrd")], 0, "not recorded in its row"))

    # ---- small ones --------------------------------------------------------------------------------------------
    for name, value in (("perturb_empty", ""), ("perturb_commas", ",,,")):
        cases.append(Case(name, "small", ["run", "--model", model, "--task", "Lift", "--perturb", value], 2,
                          "names no perturbation"))
    cases.append(Case("controls_every_0", "small", ["run", "--model", model, "--task", "Lift", "--attention-controls",
                                                    "blank", "--controls-every", "0"], 2, "--controls-every must be"))
    cases.append(Case("huge_value", "small", ["run", "--model", model, "--task", "x" * 100_000], 2, "characters"))
    toml = out / "huge_value.toml"
    toml.write_text('task = "Lift"\nepisodes = "' + "9" * 500_000 + '"\n')
    cases.append(Case("huge_value_file", "small", ["run", "--protocol", str(toml)], 2, "characters"))
    ckpt = out / "many_layers"
    shutil.copytree(model, ckpt)
    config = json.loads((ckpt / "config.json").read_text())
    config["model"]["transformer_kwargs"]["num_layers"] = 10000
    (ckpt / "config.json").write_text(json.dumps(config))
    cases.append(Case("many_layers", "small", ["run", "--model", str(ckpt), "--task", "Lift", "--max-steps", "2",
                                               "--out", str(out / "many_layers.out")], 2, "encoder blocks"))
    return cases


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit("usage: hostile_corpus.py RUN_DIR OUT_DIR MODEL_DIR")
    for case in make_cases(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]):
        print(f"{case.name:<24} {case.cls:<16} exit {case.code}  octo-harness {' '.join(a[:60] for a in case.argv)}")

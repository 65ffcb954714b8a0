"""The reference policy's training loop (reference_policies.train): the steps, the loss curve, the periodic
checkpoints, and the run's resumable state saved with each checkpoint, so that a run killed at any moment resumes
at its latest checkpoint and ends with the same bytes as a run that was never stopped (on one machine).

`<out>/train_state.msgpack` holds the step, the trainable parameters, the optimiser's state, the JAX key, the batch
sampler's generator state, the loss curve so far (and the losses of the log window in progress) and the training
seconds so far. It is written to a temporary file and renamed into place, so a kill leaves the previous state or the
new one, never half of one. Its fingerprint covers the configuration, the training data (actions, proprio, tasks,
frame weights, chunk masks, normalisation statistics, image shapes), the instructions, the statistics key and the
conventions; a state of any other run is ignored (logged) and training starts at step 1. The file is removed when
training ends: a finished checkpoint folder holds only the checkpoint.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
import shutil
import time
from dataclasses import asdict
from pathlib import Path

import jax
import numpy as np
from flax import serialization

from harness.files import write_atomic

log = logging.getLogger(__name__)

STATE_FILE = "train_state.msgpack"
FORMAT = "octo-harness-train-state/2"  # 2: no schedule count in the optimiser state


class Loop:
    """The steps of one training run into `out_dir` (checkpoints every `cfg.checkpoint_every`, curve rows every
    `cfg.log_every`), resumed from the state a stopped run with the same fingerprint `fp` saved there."""

    def __init__(self, out_dir: Path, fp: str, cfg, schedule, t5_params: dict):
        self.out_dir, self.fp, self.cfg, self.schedule, self.t5_params = out_dir, fp, cfg, schedule, t5_params

    def run(self, train_step, sample_batch, rng: np.random.Generator, key, trainable, opt_state, on_step=None):
        """Steps to `cfg.steps` (from the saved state's step where there is one); `sample_batch()` draws from
        `rng`, whose state is saved and restored with the rest; `train_step` is train_step.make_train_step's, handed
        the updates made before (0 at step 1). Returns (trainable, curve rows, training seconds)."""
        cfg, out_dir = self.cfg, self.out_dir
        rows, window, done, before = [], [], 0, 0.0
        resumed = load(out_dir, self.fp, trainable=trainable, opt_state=opt_state)
        if resumed is not None:
            trainable, opt_state, key = resumed["trainable"], resumed["opt_state"], resumed["key"]
            rows, window, done, before = resumed["rows"], resumed["window"], resumed["step"], resumed["seconds"]
            rng.bit_generator.state = resumed["rng"]
        t0 = time.perf_counter() - before
        for step in range(done + 1, cfg.steps + 1):
            key, step_key = jax.random.split(key)
            trainable, opt_state, loss = train_step(trainable, opt_state, sample_batch(), step_key, step - 1)
            window.append(loss)
            if step % cfg.log_every == 0 or step == cfg.steps:
                mean = float(np.mean(jax.device_get(window)))
                window = []
                rows.append({"step": step, "loss": round(mean, 6), "lr": float(self.schedule(step)),
                             "seconds": round(time.perf_counter() - t0, 1)})
                log.info("step %d loss %.4f (%.2f s/step)", step, mean, (time.perf_counter() - t0) / step)
                write_curve(out_dir, rows)
            if step % cfg.checkpoint_every == 0 or step == cfg.steps:
                language = {**trainable["octo_transformer"], "task_tokenizers_language": self.t5_params}
                write_params(out_dir, step, {**trainable, "octo_transformer": language})
                save(out_dir, self.fp, step, trainable=trainable, opt_state=opt_state, key=key, rng=rng, rows=rows,
                     window=window, seconds=time.perf_counter() - t0)
                log.info("checkpoint %d written", step)
            if on_step is not None:
                on_step(step)
        (out_dir / STATE_FILE).unlink(missing_ok=True)
        return trainable, rows, time.perf_counter() - t0


def fingerprint(cfg, data, texts: list[str], dataset_key: str, conventions: str | None) -> str:
    """sha256 of what a training run's steps depend on (besides the code and the machine)."""
    h = hashlib.sha256(json.dumps([FORMAT, asdict(cfg), texts, dataset_key, conventions], default=str).encode())
    arrays = [data.actions, data.proprio, data.task, data.action_mask]
    if data.weight is not None:
        arrays.append(data.weight)
    for array in arrays:
        h.update(str((array.dtype, array.shape)).encode())
        h.update(np.ascontiguousarray(array).tobytes())
    h.update(json.dumps(data.statistics, default=lambda a: np.asarray(a).tolist()).encode())
    for key in sorted(data.images):
        h.update(str((key, data.images[key].shape)).encode())
    return h.hexdigest()


def save(out_dir: Path, fp: str, step: int, *, trainable, opt_state, key, rng: np.random.Generator, rows: list[dict],
         window: list, seconds: float) -> None:
    """Write the state after `step` (atomically)."""
    state = {"format": FORMAT, "fingerprint": fp, "step": step, "seconds": seconds,
             "trainable": serialization.to_state_dict(jax.device_get(trainable)),
             "opt_state": serialization.to_state_dict(jax.device_get(opt_state)),
             "key": np.asarray(jax.device_get(key)),
             "window": np.asarray(jax.device_get(window), np.float32).reshape(-1),
             "rng": json.dumps(rng.bit_generator.state), "rows": json.dumps(rows)}
    write_atomic(out_dir / STATE_FILE, lambda f: f.write(serialization.msgpack_serialize(state)))


def load(out_dir: Path, fp: str, *, trainable, opt_state) -> dict | None:
    """The state saved in `out_dir` by a run with fingerprint `fp`, restored onto the templates `trainable` and
    `opt_state`, or None (no state, another run's, or unreadable: each logged)."""
    path = out_dir / STATE_FILE
    if not path.is_file():
        return None
    # parameters, Adam's two moments and a little more: anything much larger is not this run's state
    limit = 4 * 4 * sum(int(np.size(x)) for x in jax.tree.leaves(trainable)) + 2**20
    if path.stat().st_size > limit:
        log.warning("%s is %d bytes, more than this run's state can be (%d): starting at step 1", path,
                    path.stat().st_size, limit)
        return None
    try:
        state = serialization.msgpack_restore(path.read_bytes())
        if state.get("format") != FORMAT:
            log.warning("%s was saved by another version of the trainer (%s; this one writes %s): starting at step 1",
                        path, state.get("format"), FORMAT)
            return None
        if state.get("fingerprint") != fp:
            log.warning("%s belongs to another training run (configuration or data differ): starting at step 1", path)
            return None
        restored = {"step": int(state["step"]), "seconds": float(state["seconds"]),
                    "trainable": serialization.from_state_dict(trainable, state["trainable"]),
                    "opt_state": serialization.from_state_dict(opt_state, state["opt_state"]),
                    "key": np.asarray(state["key"], np.uint32), "rows": json.loads(state["rows"]),
                    "window": list(np.asarray(state["window"], np.float32)),
                    "rng": json.loads(state["rng"])}
    except Exception as e:  # noqa: BLE001 - any damage to the file means: start again
        log.warning("%s is unreadable (%s): starting at step 1", path, e)
        return None
    log.info("resuming the training in %s at step %d", out_dir, restored["step"])
    return restored


def write_params(folder: Path, step: int, params: dict, keep_previous: bool = False) -> Path:
    """<step>/default/checkpoint (one msgpack blob, as orbax's aggregate file); older steps removed."""
    tree = jax.tree.map(lambda x: np.asarray(x, np.float32), params)
    target = folder / str(step) / "default"
    tmp = folder / f".tmp-{step}"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "default").mkdir(parents=True)
    (tmp / "default" / "checkpoint").write_bytes(serialization.msgpack_serialize(tree))
    shutil.rmtree(folder / str(step), ignore_errors=True)
    tmp.rename(folder / str(step))
    if not keep_previous:
        for p in folder.iterdir():
            if p.is_dir() and p.name.isdigit() and int(p.name) != step:
                shutil.rmtree(p)
    return target


def write_curve(folder: Path, rows: list[dict]) -> None:
    def write(f) -> None:
        text = io.StringIO(newline="")
        writer = csv.DictWriter(text, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
        f.write(text.getvalue().encode())

    write_atomic(folder / "training_curve.csv", write)


def plot_curve(folder: Path, rows: list[dict], head: str = "l1",
               title: str = "octo-reference-robosuite: training curve") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=120)
    ax.plot([r["step"] for r in rows], [r["loss"] for r in rows], lw=1.2)
    ax.set_yscale("log")
    ax.set_xlabel("training step")
    every = rows[1]["step"] - rows[0]["step"] if len(rows) > 1 else 1
    ax.set_ylabel(f"{'L1' if head == 'l1' else 'diffusion'} loss (mean of {every} steps)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(folder / "training_curve.png")
    plt.close(fig)

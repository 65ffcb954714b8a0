"""Train the reference policy: a small Octo-architecture model, from scratch, on the scripted demonstrations.

The forward pass (reference_policies.train_step) is the runtime's own Flax modules (`OctoTransformer`,
`pool_readouts`, `ScoreNetwork`), so parameter names are Octo's and `harness.octo.load_pretrained(folder)` reads the
result. Heads and losses are Octo's, over the valid (not past the episode's end) entries of each action chunk:
  "l1" (default, L1ActionHead as in Octo's finetuning example): mean |prediction - normalised action|;
  "diffusion" (DiffusionActionHead.loss): t ~ U{0..steps-1}, x_t = sqrt(a_t) x_0 + sqrt(1 - a_t) eps, MSE
  between the predicted and the true eps. At this CPU budget (2000 steps) the diffusion head did not
  sample usable actions: Octo's 20-step cosine sampler divides its first step by sqrt(alpha_19) = 0.032,
  so an eps error of 0.14 (measured at t = 19) becomes ~4 normalised units and the chain saturates at
  +-max_action. The L1 head has no such amplification and learns the scripted experts in minutes.
The T5 encoder is tiny, randomly initialised and frozen (Octo's `finetune_encoder=False`): its encodings
of the instructions are computed once.

Output: Octo's save_pretrained layout,
  config.json (ModuleSpecs), example_batch.msgpack (the first training batch's first element, as Octo's:
  reference_policies.example_batch), dataset_statistics.json {DATASET_KEY: {action,
  proprio, num_transitions, num_trajectories}}, <step>/default/checkpoint (msgpack param dict),
  t5-tiny/config.json (HF T5 config, LanguageTokenizer encoder="t5-tiny"), tokenizer/tokenizer.json
  (word-level, T5's special ids; text_processor tokenizer_name="tokenizer"), harness.toml (evaluation
  conventions: robosuite action space, statistics key),
  training_curve.csv (step, loss, lr, seconds), training_curve.png.
Periodic checkpoints replace the previous step folder, so a killed run keeps its latest weights; with each one
goes the run's state (train_state.msgpack, removed at the end), from which calling train again resumes.
"""

from __future__ import annotations

import functools
import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization

from harness.files import atomic_write_json
from harness.octo.config import OctoConfig
from harness.octo.network import LanguageTokenizer, init_params
from harness.octo.t5 import T5Config
from harness.options import option
from reference_policies import train_loop
from reference_policies.example_batch import example_batch_from
from reference_policies.train_step import make_optimizer, make_train_step
from reference_policies.warm_start import initialise

log = logging.getLogger(__name__)

DATASET_KEY = "robosuite_reference"
T5_FOLDER = "t5-tiny"
TOKENIZER_FOLDER = "tokenizer"
LANGUAGE_TOKENS = 16
PROPRIO_DIM = 8
ACTION_DIM = 7
SPECIALS = ("<pad>", "</s>", "<unk>")  # T5's ids 0, 1, 2


@dataclass(frozen=True)
class TrainConfig:
    # warm-started (scripts/train_reference.sh); the 64-px parent trained 14000 from scratch
    steps: int = option(6000, "--steps", "training steps", type=int)
    batch_size: int = option(32, "--batch-size", "frames per training batch", type=int)
    learning_rate: float = option(6e-4, "--learning-rate", "peak learning rate of the warm-up + cosine schedule",
                                  type=float)
    warmup_steps: int = 200
    weight_decay: float = 1e-4
    grad_clip: float = 1.0
    seed: int = option(0, "--seed", "training seed (batch sampling, initialisation, augmentation)", type=int)
    log_every: int = 50
    checkpoint_every: int = 250
    shift_pixels: int = 4  # random-shift augmentation (pad + random crop) of every camera image
    paraphrase_probability: float = 0.25  # train on a paraphrase of the task's instruction this often
    # architecture
    width: int = 128
    layers: int = 4
    heads: int = 4
    mlp_dim: int = 256
    stem_features: tuple[int, ...] = (32, 32, 64, 128)
    # primary 128 px -> 8x8 patches of 16 px, wrist 64 px -> 4x4 (DemoConfig.image_sizes matches)
    image_sizes: tuple[tuple[str, int], ...] = (("image_primary", 128), ("image_wrist", 64))
    action_horizon: int = 4
    head: str = "l1"  # "l1" (Octo's L1ActionHead) or "diffusion" (DiffusionActionHead; see the module docstring)
    head_hidden: int = 256  # diffusion head only
    t5_width: int = 64
    # batches sample tasks in these proportions (then frames uniformly within a task)
    task_weights: tuple[tuple[str, float], ...] = (("Lift", 1.0), ("Stack", 1.5), ("PickPlaceCan", 2.0))
    # warm start: copy an earlier checkpoint's parameters (reference_policies.warm_start); None = from scratch
    init_from: str | None = option(None, "--init-from", "warm start from this checkpoint folder (same architecture; "
                                   "patch-grid position embeddings are resampled to the new image sizes)",
                                   metavar="CHECKPOINT", default_text="none: random initialisation")

    def __post_init__(self) -> None:
        if self.steps < 1 or self.batch_size < 1 or not self.learning_rate >= 0:  # rate 0: the initial weights kept
            raise ValueError(f"--steps {self.steps}, --batch-size {self.batch_size}, --learning-rate "
                             f"{self.learning_rate}: steps and batch size must be >= 1, the learning rate >= 0")


# ----------------------------------------------------------------------------- config and text


def _spec(module: str, name: str, **kwargs) -> dict:
    return {"module": module, "name": name, "args": [], "kwargs": kwargs}


def model_config(cfg: TrainConfig) -> dict:
    """config.json contents (Octo ModuleSpecs) of the reference architecture."""
    tok = "octo.model.components.tokenizers"
    images = {}
    for key, _ in cfg.image_sizes:
        stem = _spec("octo.model.components.vit_encoders", "SmallStem16", features=list(cfg.stem_features),
                     num_features=cfg.width)
        images[key.removeprefix("image_")] = _spec(tok, "ImageTokenizer", obs_stack_keys=[key], task_stack_keys=[],
                                                   encoder=stem)
    return {
        "model": {
            "observation_tokenizers": {
                **images,
                "proprio": _spec(tok, "LowdimObsTokenizer", obs_keys=["proprio"], discretize=False),
            },
            "task_tokenizers": {"language": _spec(tok, "LanguageTokenizer", encoder=T5_FOLDER, finetune_encoder=False)},
            "heads": {"action": _head_spec(cfg)},
            "readouts": {"action": 1},
            "token_embedding_size": cfg.width,
            "transformer_kwargs": {"num_layers": cfg.layers, "mlp_dim": cfg.mlp_dim, "num_attention_heads": cfg.heads,
                                   "dropout_rate": 0.0, "attention_dropout_rate": 0.0, "add_position_embedding": False},
            "max_horizon": 10,
            "repeat_task_tokens": False,
            "use_correct_attention": True,
        },
        "text_processor": _spec("octo.data.utils.text_processing", "HFTokenizer", tokenizer_name=TOKENIZER_FOLDER,
                                encode_with_model=False,
                                tokenizer_kwargs={"max_length": LANGUAGE_TOKENS, "padding": "max_length",
                                                  "truncation": True, "return_tensors": "np"}),
        "window_size": 1,
    }


def conventions_toml(cfg: TrainConfig) -> str:
    """harness.toml: how octo-harness evaluates this checkpoint (see harness.conventions)."""
    sizes = dict(cfg.image_sizes)
    return (
        '# How octo-harness evaluates this checkpoint (trained on robosuite OSC_POSE inputs, default cameras\n'
        f'# agentview 256 px resized to {sizes["image_primary"]} px and eye-in-hand 128 px resized to {sizes["image_wrist"]} px,\n'
        '# upright images, fast render).\n'
        'format = "octo-harness-conventions/1"\n\n'
        '[env]\naction_space = "robosuite"\nimage_convention = "upright"\n\n'
        f'[policy]\ndataset_key = "{DATASET_KEY}"\naction_normalization = "normal"\nproprio_normalization = "normal"\n'
    )


def _head_spec(cfg: TrainConfig) -> dict:
    heads = "octo.model.components.action_heads"
    if cfg.head == "diffusion":
        return _spec(heads, "DiffusionActionHead", readout_key="readout_action", use_map=False,
                     action_horizon=cfg.action_horizon, action_dim=ACTION_DIM, n_diffusion_samples=1, dropout_rate=0.0,
                     hidden_dim=cfg.head_hidden)
    if cfg.head == "l1":
        return _spec(heads, "L1ActionHead", readout_key="readout_action", use_map=False,
                     action_horizon=cfg.action_horizon, action_dim=ACTION_DIM, max_action=5.0)
    raise ValueError(f"unknown head {cfg.head!r}; use 'l1' or 'diffusion'")


def words(text: str) -> list[str]:
    import re

    return re.findall(r"\w+", text.lower())


def build_tokenizer(texts: list[str]):
    """Word-level `tokenizers.Tokenizer` over the words of `texts`, with T5's <pad>=0 </s>=1 <unk>=2, appending </s>."""
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, processors

    vocab = {s: i for i, s in enumerate(SPECIALS)}
    for text in texts:
        for w in words(text):
            vocab.setdefault(w, len(vocab))
    tok = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tok.normalizer = normalizers.Lowercase()
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.post_processor = processors.TemplateProcessing(single="$A </s>", special_tokens=[("</s>", 1)])
    return tok


def t5_config_dict(vocab_size: int, width: int) -> dict:
    """Hugging Face T5 config.json of the tiny frozen encoder."""
    return {"architectures": ["T5EncoderModel"], "model_type": "t5", "vocab_size": vocab_size, "d_model": width,
            "d_kv": width // 4, "d_ff": 2 * width, "num_layers": 2, "num_decoder_layers": 2, "num_heads": 4,
            "relative_attention_num_buckets": 32, "relative_attention_max_distance": 128, "layer_norm_epsilon": 1e-6,
            "feed_forward_proj": "relu", "dropout_rate": 0.0, "is_encoder_decoder": True, "pad_token_id": 0,
            "eos_token_id": 1, "decoder_start_token_id": 0, "initializer_factor": 1.0}


def task_instructions() -> dict[str, tuple[str, ...]]:
    """{task: (default instruction, paraphrases...)} from the env's task registry."""
    from envs.resolver import get_task
    from reference_policies.experts import EXPERT_TASKS

    return {t: (get_task(t).instruction, *get_task(t).paraphrases) for t in EXPERT_TASKS}


# ----------------------------------------------------------------------------- data


@dataclass(frozen=True, eq=False)
class Dataset:
    images: dict  # {key: (n, S, S, 3) uint8}
    proprio: np.ndarray  # (n, 8) float32, normalised
    actions: np.ndarray  # (n, horizon, 7) float32, normalised chunks
    action_mask: np.ndarray  # (n, horizon) bool, False past the episode's end
    task: np.ndarray  # (n,) int32 index into the task list
    statistics: dict
    weight: np.ndarray | None = None  # (n,) float64 sampling weight within its task; None: uniform (demonstrations)


def frame_drawer(by_task: list[np.ndarray], weight: np.ndarray | None):
    """`draw(tasks, rng) -> frame indices`: for each drawn task, one of its frames (`by_task[t]`), uniformly when
    `weight` is None (the draws of every policy trained before frame weights), else with probability proportional
    to the frame's weight within its task."""
    if weight is None:
        return lambda tasks, rng: np.array([by_task[t][rng.integers(0, len(by_task[t]))] for t in tasks])
    cdf = [np.cumsum(weight[f]) / weight[f].sum() for f in by_task]
    return lambda tasks, rng: np.array([by_task[t][min(np.searchsorted(cdf[t], rng.random(), side="right"),
                                                       len(by_task[t]) - 1)] for t in tasks])


def _stats(x: np.ndarray, mask: np.ndarray) -> dict:
    return {"mean": x.mean(0), "std": np.maximum(x.std(0), 1e-6), "max": x.max(0), "min": x.min(0),
            "p99": np.percentile(x, 99, axis=0), "p01": np.percentile(x, 1, axis=0), "mask": mask}


def build_dataset(demos: dict[str, dict[str, np.ndarray]], horizon: int,
                  normalise_with: dict[str, dict[str, np.ndarray]] | None = None,
                  dataset_key: str = DATASET_KEY) -> Dataset:
    """Concatenate all tasks; action chunks a[t:t+horizon] (masked past the end); mean/std normalisation.

    `normalise_with` (default `demos`): the data whose action and proprio statistics normalise (DAgger
    fine-tuning keeps the demonstrations' statistics, so the warm-started head's units do not move).
    """
    tasks = list(demos)
    keys = [k for k in demos[tasks[0]] if k.startswith("image_")]
    images = {k: np.concatenate([demos[t][k] for t in tasks]) for k in keys}
    proprio = np.concatenate([demos[t]["proprio"] for t in tasks]).astype(np.float32)
    actions = np.concatenate([demos[t]["action"] for t in tasks]).astype(np.float32)
    episode = np.concatenate([demos[t]["episode"] + 10_000 * i for i, t in enumerate(tasks)])
    task = np.concatenate([np.full(len(demos[t]["action"]), i, np.int32) for i, t in enumerate(tasks)])
    n = len(actions)
    raw_index = np.arange(n)[:, None] + np.arange(horizon)[None]  # (n, horizon)
    index = np.minimum(raw_index, n - 1)
    valid = (raw_index < n) & (episode[index] == episode[:, None])
    index = np.where(valid, index, np.arange(n)[:, None])  # past the end: hold the last valid index
    last = np.maximum.accumulate(np.where(valid, index, -1), axis=1)
    chunks = actions[last]
    action_mask = np.ones(ACTION_DIM, bool)
    action_mask[-1] = False  # gripper stays as is (-1 open / +1 closed), as Octo leaves it unnormalised
    if normalise_with is None:
        reference_actions, reference_proprio = actions, proprio
    else:
        reference_actions = np.concatenate([a["action"] for a in normalise_with.values()]).astype(np.float32)
        reference_proprio = np.concatenate([a["proprio"] for a in normalise_with.values()]).astype(np.float32)
    action_stats = _stats(reference_actions, action_mask)
    proprio_stats = _stats(reference_proprio, np.ones(PROPRIO_DIM, bool))
    norm_actions = np.where(action_mask, (chunks - action_stats["mean"]) / action_stats["std"], chunks)
    norm_proprio = (proprio - proprio_stats["mean"]) / proprio_stats["std"]
    statistics = {dataset_key: {
        "action": action_stats, "proprio": proprio_stats, "num_transitions": n,
        "num_trajectories": int(sum(len(demos[t]["lengths"]) for t in tasks)),
    }}
    weight = None  # frames that carry a "weight" (DAgger corrections near the grasp) are drawn more often
    if any("weight" in demos[t] for t in tasks):
        weight = np.concatenate([np.asarray(demos[t].get("weight", np.ones(len(demos[t]["action"]))), np.float64)
                                 for t in tasks])
        if not (np.all(np.isfinite(weight)) and np.all(weight > 0)):
            raise ValueError("frame weights must be finite and > 0")
    return Dataset(images, norm_proprio.astype(np.float32), norm_actions.astype(np.float32), valid, task, statistics,
                   weight)


# ----------------------------------------------------------------------------- parameters


def split_t5(params: dict, language: str = "language") -> tuple[dict, dict]:
    """(trainable params, frozen T5 subtree)."""
    backbone = dict(params["octo_transformer"])
    t5 = backbone.pop(f"task_tokenizers_{language}")
    return {**params, "octo_transformer": backbone}, t5


# ----------------------------------------------------------------------------- saving


def _to_lists(node):
    if isinstance(node, dict):
        return {k: _to_lists(v) for k, v in node.items()}
    if isinstance(node, (np.ndarray, jax.Array)):
        return np.asarray(node).tolist()
    if isinstance(node, np.generic):
        return node.item()
    return node


def write_static_files(folder: Path, config_dict: dict, tokenizer, t5_dict: dict, statistics: dict,
                       example_batch: dict) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.json").write_text(json.dumps(config_dict, indent=2))
    (folder / "dataset_statistics.json").write_text(json.dumps(_to_lists(statistics), indent=2))
    (folder / "example_batch.msgpack").write_bytes(serialization.msgpack_serialize(example_batch))
    (folder / T5_FOLDER).mkdir(exist_ok=True)
    (folder / T5_FOLDER / "config.json").write_text(json.dumps(t5_dict, indent=2))
    (folder / TOKENIZER_FOLDER).mkdir(exist_ok=True)
    tokenizer.save(str(folder / TOKENIZER_FOLDER / "tokenizer.json"))
    (folder / TOKENIZER_FOLDER / "tokenizer_config.json").write_text(json.dumps(
        {"tokenizer_class": "PreTrainedTokenizerFast", "pad_token": "<pad>", "eos_token": "</s>", "unk_token": "<unk>",
         "model_max_length": LANGUAGE_TOKENS}, indent=2))


# ----------------------------------------------------------------------------- training


def train(demos: dict[str, dict[str, np.ndarray]], out_dir: str | Path, cfg: TrainConfig = TrainConfig(),
          extra_files: dict[str, str] | None = None,
          normalise_with: dict[str, dict[str, np.ndarray]] | None = None,
          instructions: dict[str, tuple[str, ...]] | None = None, dataset_key: str = DATASET_KEY,
          conventions: str | None = None, on_step=None) -> dict:
    """Train on `demos` ({task: arrays from demos.load_demos}) and save into `out_dir`; returns a summary.

    `normalise_with`: the data whose statistics normalise actions and proprio (default `demos`).
    `instructions`: {task: (instruction, paraphrases...)}, the same number per task (default: the robosuite
    tasks' from the registry); `dataset_key`: the statistics key; `conventions`: harness.toml's text (default:
    the robosuite reference's, `conventions_toml(cfg)`). `on_step(step)` is called after every step.
    A run stopped at any moment resumes at its latest checkpoint when called again with the same arguments
    (reference_policies.train_loop), and ends with the same bytes as an unstopped run.
    """
    out_dir = Path(out_dir)
    start = time.perf_counter()
    instructions = instructions or task_instructions()
    tasks = list(demos)
    texts = [s for t in tasks for s in instructions[t]]  # per task: default, then paraphrases
    per_task = len(instructions[tasks[0]])
    if any(len(instructions[t]) != per_task for t in tasks):
        raise ValueError("every task needs as many paraphrases as the others")
    tokenizer = build_tokenizer(texts)
    vocab = tokenizer.get_vocab_size()
    t5_dict = t5_config_dict(vocab, cfg.t5_width)
    t5 = T5Config.from_hf_dict(t5_dict)
    config_dict = model_config(cfg)
    config = OctoConfig.from_dict(config_dict)
    data = build_dataset(demos, cfg.action_horizon, normalise_with, dataset_key)
    sizes = dict(cfg.image_sizes)

    key = jax.random.PRNGKey(cfg.seed)
    init_key, key = jax.random.split(key)
    params, warm = initialise(init_key, _initialiser(config, tuple(sizes.items()), t5), cfg.init_from)
    trainable, t5_params = split_t5(params)
    n_params = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(params))
    log.info("reference model: %d parameters (%.1f MB float32), %d frames, vocab %d", n_params, n_params * 4 / 2**20,
             len(data.actions), vocab)

    # the example batch: the first batch the training's sampler draws, from a sampler of its own (the training's
    # random state is left as it was)
    first = _batch_sampler(data, tasks, per_task, cfg, np.random.default_rng(cfg.seed))()
    encodings = _write_model_files(out_dir, config_dict, tokenizer, t5, t5_dict, t5_params, data.statistics, texts,
                                   first)
    (out_dir / "harness.toml").write_text(conventions if conventions is not None else conventions_toml(cfg))
    for name, content in (extra_files or {}).items():
        (out_dir / name).write_text(content)

    warmup = min(cfg.warmup_steps, cfg.steps - 1)  # optax needs a decay phase of at least one step
    schedule = optax.warmup_cosine_decay_schedule(0.0, cfg.learning_rate, warmup, cfg.steps,
                                                  cfg.learning_rate * 0.05)
    optimizer = make_optimizer(cfg.grad_clip, cfg.weight_decay)
    opt_state = optimizer.init(trainable)
    train_step = make_train_step(config, optimizer, schedule, encodings, tuple(sizes), cfg.shift_pixels)
    rng = np.random.default_rng(cfg.seed)
    sample_batch = _batch_sampler(data, tasks, per_task, cfg, rng)

    fp = train_loop.fingerprint(cfg, data, texts, dataset_key, conventions)
    loop = train_loop.Loop(out_dir, fp, cfg, schedule, t5_params)
    looped = time.perf_counter()
    trainable, rows, seconds = loop.run(train_step, sample_batch, rng, key, trainable, opt_state, on_step)
    looped = time.perf_counter() - looped  # this call's share of `seconds` (a resumed run counts earlier calls too)
    train_loop.plot_curve(out_dir, rows, cfg.head, title=f"{out_dir.name}: training curve")
    summary = {"parameters": n_params, "frames": int(len(data.actions)), "train_seconds": seconds,
               "total_seconds": time.perf_counter() - start - looped + seconds, "final_loss": rows[-1]["loss"],
               "config": asdict(cfg), "warm_start": warm}
    atomic_write_json(out_dir / "training_summary.json", summary, exact=True)
    return summary


@functools.lru_cache(maxsize=8)
def _initialiser(config: OctoConfig, sizes: tuple[tuple[str, int], ...], t5: T5Config):
    """rng -> fresh parameters of the network (`init_params`), one function per (frozen) configuration in a process,
    so that warm_start.initialise's compiled initialiser serves every training of the same network (a DAgger
    round's trainings) instead of being traced and lowered again for each (a few seconds of CPU each)."""
    return lambda rng: init_params(rng, config, {k: (s, s) for k, s in sizes}, 1, t5_config=t5,
                                   lowdim_sizes={"proprio": PROPRIO_DIM}, language_tokens=LANGUAGE_TOKENS)


def _write_model_files(out_dir: Path, config_dict: dict, tokenizer, t5: T5Config, t5_dict: dict, t5_params: dict,
                       statistics: dict, texts: list[str], first_batch: dict) -> jax.Array:
    """The checkpoint's files but its parameters (config.json, dataset statistics, tokenizer, T5 config, and the
    example batch: `first_batch`'s first element, reference_policies.example_batch); returns the frozen T5's
    encodings of `texts` (k, tokens, d_t5), tokenised by the runtime's own tokenizer read back from the folder (its
    padding and truncation)."""
    from harness.octo.text import load_text_tokenizer

    write_static_files(out_dir, config_dict, tokenizer, t5_dict, statistics, {})
    text = load_text_tokenizer(str(out_dir / TOKENIZER_FOLDER / "tokenizer.json"), LANGUAGE_TOKENS)
    encoded = text.encode(texts)
    encodings = LanguageTokenizer(t5).apply({"params": t5_params}, jnp.asarray(encoded["input_ids"]),
                                            jnp.asarray(encoded["attention_mask"]))  # (k, tokens, d_t5)
    write_static_files(out_dir, config_dict, tokenizer, t5_dict, statistics, example_batch_from(first_batch, encoded))
    return encodings


def _batch_sampler(data: Dataset, tasks: list[str], per_task: int, cfg: TrainConfig, rng: np.random.Generator):
    """`sample_batch() -> batch` drawn from `rng` (seeded with `cfg.seed`; the loop saves its state): tasks in
    `cfg.task_weights`' proportions, frames within a task by `frame_drawer`, a paraphrase of the instruction with
    `cfg.paraphrase_probability`."""
    by_task = [np.flatnonzero(data.task == i) for i in range(len(tasks))]

    weights = dict(cfg.task_weights)
    p_task = np.array([weights.get(t, 1.0) for t in tasks], np.float64)
    p_task /= p_task.sum()

    draw = frame_drawer(by_task, data.weight)
    image_keys = [k for k, _ in cfg.image_sizes]

    def sample_batch():
        task = rng.choice(len(tasks), cfg.batch_size, p=p_task)
        idx = draw(task, rng)
        phrase = (np.where(rng.random(cfg.batch_size) < cfg.paraphrase_probability,
                           rng.integers(1, per_task, cfg.batch_size), 0) if per_task > 1
                  else np.zeros(cfg.batch_size, np.int64))
        return {
            **{k: data.images[k][idx][:, None] for k in image_keys},
            "proprio": data.proprio[idx][:, None],
            "actions": data.actions[idx],
            "action_mask": data.action_mask[idx],
            "instruction": (data.task[idx] * per_task + phrase).astype(np.int32),
        }

    return sample_batch

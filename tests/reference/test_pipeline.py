"""Reference policy pipeline: scripted experts in the real simulator, demonstration recording, dataset
chunks and statistics, and a tiny training run that reduces the loss and saves a loadable Octo checkpoint."""

import time
from dataclasses import replace

import numpy as np
import pytest

import envs
from reference_policies import demos as demos_mod
from reference_policies.experts import EXPERT_TASKS, ExpertConfig, ScriptedExpert
from reference_policies.train import DATASET_KEY, TrainConfig, build_dataset, build_tokenizer, train


def _expert_succeeds(task: str, seed: int) -> bool:
    env = envs.make(task, cameras={}, action_space="robosuite")
    try:
        obs, info = env.reset(seed=seed)
        expert = ScriptedExpert(task)
        expert.reset(obs, env)
        for _ in range(env.max_episode_steps):
            obs, _, terminated, truncated, info = env.step(expert.act(obs, env))
            if terminated or truncated:
                break
        return bool(info["success"])
    finally:
        env.close()


@pytest.mark.slow
@pytest.mark.parametrize("task,seed", [("Lift", 3), ("Stack", 4), ("PickPlaceCan", 5)])
def test_expert_succeeds_in_the_simulator(task, seed):
    assert _expert_succeeds(task, seed)


def test_expert_rejects_an_unknown_task():
    with pytest.raises(ValueError, match="no scripted expert"):
        ScriptedExpert("Door")


def test_training_seeds_are_disjoint_from_evaluation_seeds():
    config = demos_mod.DemoConfig()
    blocks = []
    for task in EXPERT_TASKS:
        base = config.task_seed_base(task)
        blocks.append((base, base + config.jobs_per_task * demos_mod.SEEDS_PER_JOB))
    assert all(low >= demos_mod.EVAL_SEEDS for low, _ in blocks)
    blocks.sort()
    assert all(a_high <= b_low for (_, a_high), (b_low, _) in zip(blocks, blocks[1:]))


@pytest.fixture(scope="module")
def lift_episode():
    """One scripted Lift demonstration recorded as the policy sees it (64 px both cameras), or None."""
    env = envs.make("Lift", fast_render=True, action_space="robosuite", max_episode_steps=120)
    try:
        return demos_mod.record_episode(env, ScriptedExpert("Lift"), 100_000, {"image_primary": 64, "image_wrist": 64},
                                        noise=0.2, max_steps=120)
    finally:
        env.close()


@pytest.mark.slow
def test_recorded_episode_is_what_the_policy_sees(lift_episode):
    episode = lift_episode
    assert episode is not None
    n = len(episode["action"])
    assert 10 < n < 120
    assert episode["image_primary"].shape == (n, 64, 64, 3) and episode["image_primary"].dtype == np.uint8
    assert episode["image_wrist"].shape == (n, 64, 64, 3) and episode["image_wrist"].dtype == np.uint8
    assert episode["proprio"].shape == (n, 8) and episode["proprio"].dtype == np.float32
    assert episode["action"].shape == (n, 7) and episode["action"].dtype == np.float32
    assert np.all(np.abs(episode["action"]) <= 1.0)
    assert set(np.unique(episode["action"][:, 6])) == {-1.0, 1.0}  # opens, then closes
    assert episode["image_primary"].std() > 5  # a rendered scene, not a blank frame


@pytest.mark.slow
def test_the_example_batch_is_the_first_element_of_a_real_training_batch(lift_episode):
    """A training batch drawn from a real demonstration, as the trainer draws it: its first element becomes the
    example batch (example_batch.msgpack), a rendered frame per camera at the training size and orientation (the
    recorded one), with that frame's proprio, its action chunk and its instruction's tokens."""
    from reference_policies.example_batch import example_batch_from
    from reference_policies.train import _batch_sampler

    n = len(lift_episode["action"])
    demos = {"Lift": {**lift_episode, "episode": np.zeros(n, np.int32), "lengths": np.array([n], np.int32)}}
    cfg = TrainConfig(batch_size=4, image_sizes=(("image_primary", 64), ("image_wrist", 64)))
    data = build_dataset(demos, cfg.action_horizon)
    batch = _batch_sampler(data, ["Lift"], 2, replace(cfg, paraphrase_probability=1.0), np.random.default_rng(0))()
    language = {"input_ids": np.array([[5, 6, 1, 0], [7, 8, 9, 1]], np.int32), "attention_mask": np.ones((2, 4), bool)}
    example = example_batch_from(batch, language)

    obs = example["observation"]
    (i,) = [i for i in range(n) if np.array_equal(lift_episode["image_primary"][i], obs["image_primary"][0, 0])]
    assert obs["image_primary"].shape == obs["image_wrist"].shape == (1, 1, 64, 64, 3)
    assert obs["image_primary"].dtype == np.uint8 and obs["image_primary"].std() > 5  # a rendered scene, not zeros
    np.testing.assert_array_equal(obs["image_wrist"][0, 0], lift_episode["image_wrist"][i])
    np.testing.assert_array_equal(obs["proprio"][0, 0], data.proprio[i])  # normalised, as trained
    assert example["action"].shape == (1, 1, cfg.action_horizon, 7) and example["action"].dtype == np.float32
    np.testing.assert_array_equal(example["action"][0, 0], data.actions[i])
    assert np.abs(example["action"]).sum() > 0
    np.testing.assert_array_equal(example["task"]["language_instruction"]["input_ids"], [[7, 8, 9, 1]])  # paraphrase
    assert set(obs["pad_mask_dict"]) == {"image_primary", "image_wrist", "proprio"}
    with pytest.raises(ValueError, match="image_"):
        example_batch_from({"proprio": batch["proprio"]}, language)


@pytest.mark.slow
def test_recording_writes_whole_episodes_and_is_found_again(tmp_path):
    config = demos_mod.DemoConfig(tasks=("Lift",), episodes=(("Lift", 2),), jobs_per_task=2,
                                  image_sizes=(("image_primary", 32), ("image_wrist", 32)))
    summary = demos_mod.record_demos(config, tmp_path, workers=1)
    (arrays,) = demos_mod.load_demos(tmp_path, ("Lift",)).values()
    lengths = arrays["lengths"]
    assert summary["Lift"]["episodes"] == 2 and summary["Lift"]["steps"] == lengths.sum() == len(arrays["action"])
    # one seed from each job's block; episode ids and steps restart per episode
    assert list(arrays["seeds"]) == [config.task_seed_base("Lift"), config.task_seed_base("Lift") + 1000]
    assert list(arrays["episode"]) == [0] * lengths[0] + [1] * lengths[1]
    assert list(arrays["step"][lengths[0] - 1:lengths[0] + 1]) == [lengths[0] - 1, 0]
    assert arrays["image_primary"].shape == (lengths.sum(), 32, 32, 3)
    assert not list(tmp_path.glob("*.tmp.npz"))
    assert demos_mod.existing_demos(config, tmp_path) == summary
    assert demos_mod.existing_demos(demos_mod.DemoConfig(), tmp_path) is None  # another configuration
    changed_expert = replace(config, expert=ExpertConfig(bin_inset=(0.0, 0.04)))
    assert demos_mod.existing_demos(changed_expert, tmp_path) is None  # another demonstrator records afresh


def _stuck_frames(episode: dict) -> int:
    """Frames where the hand holds something and the label pushes +x at saturation while the hand does not
    move in x over the next 5 frames (pushing against the arm's reach)."""
    a, p = episode["action"], episode["proprio"]
    return sum(1 for i in range(len(a) - 5) if a[i, 6] > 0 and a[i, 0] > 0.9 and abs(p[i + 5, 0] - p[i, 0]) < 0.002)


@pytest.mark.slow
def test_can_expert_carries_to_a_point_the_arm_reaches():
    """The carry point over the can's bin is inside the arm's reach, so the carry phase ends on arrival (a
    state), not by timing out while pushing against the reach limit (a label the policy cannot read off the
    frame). Aiming at the bin's centre, as the first expert did, pushes for 20 frames on this seed. The expert and
    the check read the state only, so no camera is rendered: rendering moves no physics (the same 98- and 138-step
    episodes, 0 and 19 stuck frames, with the default cameras and without) and it was 4/5 of the time."""
    env = envs.make("PickPlaceCan", cameras={}, action_space="robosuite", max_episode_steps=300)
    try:
        record = lambda cfg: demos_mod.record_episode(env, ScriptedExpert("PickPlaceCan", cfg), 300_000,  # noqa: E731
                                                      {}, noise=0.3, max_steps=300)
        inset, centre = record(ExpertConfig()), record(ExpertConfig(bin_inset=(0.0, 0.04)))
    finally:
        env.close()
    assert inset is not None and centre is not None
    assert _stuck_frames(inset) == 0
    assert _stuck_frames(centre) >= 10
    assert len(inset["action"]) < len(centre["action"])


def _toy_demos(lengths=(3, 2), seed=0):
    """Two episodes with actions a[t] = (episode*10 + t) in every arm dim, gripper alternating."""
    rng = np.random.default_rng(seed)
    actions, episode = [], []
    for e, n in enumerate(lengths):
        for t in range(n):
            actions.append([e * 10 + t] * 6 + [1.0 if t % 2 else -1.0])
            episode.append(e)
    n = len(actions)
    return {
        "image_primary": rng.integers(0, 255, (n, 32, 32, 3), dtype=np.uint8),
        "proprio": rng.normal(size=(n, 8)).astype(np.float32),
        "action": np.array(actions, np.float32),
        "episode": np.array(episode, np.int32),
        "step": np.concatenate([np.arange(k) for k in lengths]).astype(np.int32),
        "lengths": np.array(lengths, np.int32),
        "seeds": np.arange(len(lengths)),
    }


def test_action_chunks_stop_at_the_episode_end_and_keep_the_gripper_unnormalised():
    data = build_dataset({"Lift": _toy_demos()}, horizon=3)
    stats = data.statistics[DATASET_KEY]["action"]
    raw = data.actions * np.where(stats["mask"], stats["std"], 1) + np.where(stats["mask"], stats["mean"], 0)
    # episode 0 (t = 0, 1, 2): chunk at t=1 is a[1], a[2], then a[2] held and masked out
    np.testing.assert_allclose(raw[1, :, 0], [1, 2, 2], atol=1e-5)
    assert data.action_mask[1].tolist() == [True, True, False]
    # episode 1 starts at index 3 and never reads episode 0
    np.testing.assert_allclose(raw[3, :, 0], [10, 11, 11], atol=1e-5)
    assert data.action_mask[4].tolist() == [True, False, False]
    assert stats["mask"].tolist() == [True] * 6 + [False]
    np.testing.assert_array_equal(data.actions[:, 0, 6], [-1, 1, -1, -1, 1])  # gripper as recorded
    np.testing.assert_allclose(stats["mean"][0], np.mean([0, 1, 2, 10, 11]), rtol=1e-6)
    proprio = data.statistics[DATASET_KEY]["proprio"]
    np.testing.assert_allclose(data.proprio.mean(0), 0, atol=1e-5)
    assert proprio["mask"].all()


def test_word_tokenizer_uses_t5_special_ids():
    tok = build_tokenizer(["pick up the red cube", "stack the red cube"])
    enc = tok.encode("Pick up the RED cube")
    assert enc.ids[-1] == 1 and tok.token_to_id("<pad>") == 0 and tok.token_to_id("<unk>") == 2
    assert tok.encode("pick up the blue cube").ids[3] == 2  # unknown word


# the diffusion test's small model; the warm-start test starts from its checkpoint (one training shared by both)
SMALL = dict(width=32, layers=1, heads=2, mlp_dim=64, stem_features=(32, 32, 32, 32), head="diffusion", head_hidden=32,
             t5_width=16, action_horizon=2)


@pytest.fixture(scope="module")
def diffusion(tmp_path_factory):
    """(checkpoint folder, summary, toy demo) of a 60-step diffusion-head training at 32/16 px."""
    demo = _toy_demos(lengths=(12, 10))
    demo["image_wrist"] = demo["image_primary"][:, :16, :16].copy()
    out = tmp_path_factory.mktemp("diffusion")
    cfg = TrainConfig(steps=60, batch_size=16, log_every=10, checkpoint_every=30, warmup_steps=5, learning_rate=1e-3,
                      image_sizes=(("image_primary", 32), ("image_wrist", 16)), **SMALL)
    return out, train({"Lift": demo}, out, cfg), demo


@pytest.mark.slow
def test_tiny_diffusion_training_reduces_loss_and_saves_a_loadable_octo_checkpoint(diffusion):
    """The diffusion head's training path (the committed model, tested in test_reference_model.py, uses L1)."""
    from harness.octo import load_pretrained

    out, summary, _ = diffusion
    curve = _read_curve(out / "training_curve.csv")
    assert curve[-1]["loss"] < 0.7 * curve[0]["loss"]
    assert sorted(p.name for p in out.iterdir() if p.name.isdigit()) == ["60"]  # older steps replaced
    model = load_pretrained(str(out))  # checks every parameter path and shape against config.json
    assert model.text_tokenizer.tokenizer is not None  # the tokenizer inside the checkpoint, not the fallback
    assert model.action_horizon == 2 and model.window_size == 1
    stats = model.unnormalization_statistics(DATASET_KEY)
    assert stats["mask"].tolist() == [True] * 6 + [False]
    assert summary["parameters"] == sum(int(np.prod(x.shape)) for x in __import__("jax").tree.leaves(model.params))


@pytest.mark.slow
def test_a_trained_checkpoint_carries_a_training_frame_as_its_example_batch(diffusion):
    """The trainer writes its first training batch's first element (reference_policies.example_batch), not zeros:
    the loaded model's example frames are demonstration frames at the training sizes, its action a real chunk."""
    from harness.octo.checkpoint import read_example_batch

    out, _, demo = diffusion
    batch = read_example_batch(out)
    obs = batch["observation"]
    assert np.shape(obs["image_primary"]) == (1, 1, 32, 32, 3) and np.shape(obs["image_wrist"]) == (1, 1, 16, 16, 3)
    (i,) = [i for i in range(len(demo["action"])) if np.array_equal(demo["image_primary"][i], obs["image_primary"][0, 0])]
    np.testing.assert_array_equal(obs["image_wrist"][0, 0], demo["image_wrist"][i])
    chunks = build_dataset({"Lift": demo}, horizon=2).actions
    np.testing.assert_allclose(batch["action"][0, 0], chunks[i], rtol=1e-6)
    assert np.abs(batch["action"]).sum() > 0 and np.asarray(batch["task"]["language_instruction"]["input_ids"]).any()


class _Stop(Exception):
    pass


@pytest.mark.slow
def test_a_stopped_training_resumes_at_its_checkpoint_and_ends_with_the_bytes_of_an_unstopped_one(diffusion, tmp_path,
                                                                                                    caplog):
    """Stopped after step 37 (checkpoint and state at 30), trained again with the same arguments: the same
    checkpoint bytes, curve and batches as the diffusion fixture's unstopped 60 steps; no state left at the end."""
    from reference_policies.train_loop import STATE_FILE

    source, summary, demo = diffusion
    cfg = TrainConfig(**summary["config"] | {"stem_features": tuple(summary["config"]["stem_features"]),
                                             "image_sizes": tuple(map(tuple, summary["config"]["image_sizes"])),
                                             "task_weights": tuple(map(tuple, summary["config"]["task_weights"]))})
    out = tmp_path / "stopped"

    def stop(step):
        if step == 25:
            time.sleep(12)  # training time before the checkpoint at 30: the resumed summary must count it
        if step == 37:
            raise _Stop

    with pytest.raises(_Stop):
        train({"Lift": demo}, out, cfg, on_step=stop)
    assert (out / STATE_FILE).is_file() and sorted(p.name for p in out.iterdir() if p.name.isdigit()) == ["30"]
    with caplog.at_level("INFO", logger="reference_policies.train_loop"):
        resumed = train({"Lift": demo}, out, cfg)
    assert "resuming the training in" in caplog.text and "at step 30" in caplog.text
    assert not (out / STATE_FILE).exists()
    assert (out / "60/default/checkpoint").read_bytes() == (source / "60/default/checkpoint").read_bytes()
    drop_seconds = lambda rows: [{k: v for k, v in r.items() if k != "seconds"} for r in rows]  # noqa: E731
    assert drop_seconds(_read_curve(out / "training_curve.csv")) == drop_seconds(_read_curve(source / "training_curve.csv"))
    assert resumed["final_loss"] == summary["final_loss"]
    # the whole training's seconds, both calls': total_seconds was this call's alone, less than its training seconds
    assert resumed["train_seconds"] > 12 and resumed["total_seconds"] >= resumed["train_seconds"]


def test_the_step_descends_what_adamw_with_the_schedule_would_at_each_count():
    """make_optimizer plus the rate given to the step (the schedule read on the host at the update count) is
    optax's clip + adamw(schedule), whose count lives in its state: the same parameters over warm-up and decay."""
    import jax
    import jax.numpy as jnp
    import optax

    from reference_policies.train_step import make_optimizer

    schedule = optax.warmup_cosine_decay_schedule(0.0, 3e-3, 2, 6, 1.5e-4)
    reference = optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=0.1))
    ours = make_optimizer(1.0, 0.1)
    rng = np.random.default_rng(0)
    params = {"w": jnp.asarray(rng.normal(size=(3, 4)), jnp.float32), "b": jnp.asarray(rng.normal(size=4), jnp.float32)}
    a, b = params, params
    a_state, b_state = reference.init(a), ours.init(b)
    for count in range(6):
        grads = jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape) * 3, jnp.float32), params)
        updates, a_state = reference.update(grads, a_state, a)
        a = optax.apply_updates(a, updates)
        updates, b_state = ours.update(grads, b_state, b)
        b = optax.apply_updates(b, jax.tree.map(lambda u: -jnp.float32(schedule(count)) * u, updates))
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7), a, b)
    assert not np.allclose(a["w"], params["w"])  # the rate was not 0 throughout


def test_a_training_state_of_another_run_or_a_damaged_one_is_ignored(tmp_path, caplog):
    """The fingerprint changes with the configuration and the data; a torn or foreign state starts at step 1."""
    import jax.numpy as jnp

    from reference_policies import train_loop

    demo = _toy_demos(lengths=(4, 3))
    data = build_dataset({"Lift": demo}, horizon=2)
    cfg = TrainConfig(steps=5)
    fp = train_loop.fingerprint(cfg, data, ["lift it"], DATASET_KEY, None)
    assert fp == train_loop.fingerprint(cfg, build_dataset({"Lift": _toy_demos(lengths=(4, 3))}, horizon=2),
                                        ["lift it"], DATASET_KEY, None)
    other_data = build_dataset({"Lift": {**demo, "action": demo["action"] + 1e-3}}, horizon=2)
    assert len({fp, train_loop.fingerprint(replace(cfg, learning_rate=1e-3), data, ["lift it"], DATASET_KEY, None),
                train_loop.fingerprint(cfg, other_data, ["lift it"], DATASET_KEY, None),
                train_loop.fingerprint(cfg, data, ["lift it up"], DATASET_KEY, None)}) == 4
    params, opt = {"w": jnp.ones(3)}, {"m": jnp.zeros(3)}
    rng = np.random.default_rng(0)
    train_loop.save(tmp_path, fp, 3, trainable=params, opt_state=opt, key=jnp.zeros(2, jnp.uint32), rng=rng, rows=[],
                    window=[], seconds=1.0)
    assert train_loop.load(tmp_path, fp, trainable=params, opt_state=opt)["step"] == 3
    with caplog.at_level("WARNING", logger="reference_policies.train_loop"):
        assert train_loop.load(tmp_path, "another", trainable=params, opt_state=opt) is None
        from flax import serialization  # a state of format 1 (its optimiser state held the schedule's count)

        state = tmp_path / train_loop.STATE_FILE
        saved = serialization.msgpack_restore(state.read_bytes())
        state.write_bytes(serialization.msgpack_serialize({**saved, "format": "octo-harness-train-state/1"}))
        assert train_loop.load(tmp_path, fp, trainable=params, opt_state=opt) is None
        assert "saved by another version of the trainer (octo-harness-train-state/1" in caplog.text
        state.write_bytes(state.read_bytes()[:40])  # torn
        assert train_loop.load(tmp_path, fp, trainable=params, opt_state=opt) is None
        with open(state, "r+b") as f:  # huge (sparse): refused from its size, never read
            f.truncate(2**30)
        assert train_loop.load(tmp_path, fp, trainable=params, opt_state=opt) is None
    assert "belongs to another training run" in caplog.text and "is unreadable" in caplog.text
    assert "more than this run's state can be" in caplog.text


def _read_curve(path):
    import csv

    with open(path) as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


def test_grid_embedding_resize_known_answer():
    from reference_policies.warm_start import resize_grid_embedding

    # a 2x2 grid (row-major tokens) whose value is the row index: 4x4 bilinear (half-pixel centres, edges held)
    old = np.array([0.0, 0.0, 1.0, 1.0], np.float32).reshape(1, 4, 1)
    new = resize_grid_embedding(old, 16)[0, :, 0].reshape(4, 4)
    np.testing.assert_allclose(new, np.repeat([[0.0], [0.25], [0.75], [1.0]], 4, axis=1), atol=1e-6)
    flat = np.full((1, 10, 16, 8), 0.3, np.float32)  # (1, horizon, tokens, D): a constant stays constant
    np.testing.assert_allclose(resize_grid_embedding(flat, 64), 0.3, atol=1e-6)
    with pytest.raises(ValueError, match="not square"):
        resize_grid_embedding(np.zeros((1, 6, 8)), 16)


@pytest.mark.slow
def test_warm_start_copies_an_earlier_checkpoint_and_resamples_the_patch_grid(diffusion, tmp_path):
    """A 32-px model (the diffusion test's) warm-starts a 64-px one: every parameter copied, the primary position
    embeddings resampled from 2x2 to 4x4 patches (lr 0: the saved model is the warm start itself)."""
    from flax import traverse_util

    from harness.octo.checkpoint import read_params
    from reference_policies.warm_start import resize_grid_embedding

    source, _, demo = diffusion
    small = dict(batch_size=4, log_every=1, checkpoint_every=10, warmup_steps=1, **SMALL)
    big = dict(demo, image_primary=np.repeat(np.repeat(demo["image_primary"], 2, axis=1), 2, axis=2))
    summary = train({"Lift": big}, tmp_path / "b", TrainConfig(
        steps=1, learning_rate=0.0, weight_decay=0.0, image_sizes=(("image_primary", 64), ("image_wrist", 16)),
        init_from=str(source), **small))
    a = traverse_util.flatten_dict(read_params(source, 60))
    b = traverse_util.flatten_dict(read_params(tmp_path / "b", 1))
    assert a.keys() == b.keys()
    key = ("octo_transformer", "obs_primary_pos_embedding")
    assert a[key].shape[-2:] == (4, 32) and b[key].shape[-2:] == (16, 32)
    np.testing.assert_allclose(b[key], resize_grid_embedding(a[key], 16), atol=1e-6)
    for k in a:
        if k != key:
            np.testing.assert_array_equal(a[k], b[k], err_msg="/".join(k))
    assert summary["warm_start"]["resized"] and summary["warm_start"]["copied"] == len(a) - 1
    # a checkpoint that cannot warm-start the model is refused before anything is initialised or compiled
    from jax._src import monitoring

    compiled = []

    def listen(name, seconds, **kw):
        if name.endswith("backend_compile_duration"):
            compiled.append(name)

    monitoring.register_event_duration_secs_listener(listen)
    try:
        with pytest.raises(ValueError, match="only patch-grid position embeddings can change size"):
            train({"Lift": demo}, tmp_path / "c", TrainConfig(
                steps=1, image_sizes=(("image_primary", 32), ("image_wrist", 16)), init_from=str(source),
                **{**small, "mlp_dim": 128}))
    finally:
        monitoring._unregister_event_duration_listener_by_callback(listen)
    assert compiled == []

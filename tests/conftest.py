"""Shared test set-up: offline hub, headless GL, and the reference fixture location."""

import os
from pathlib import Path

import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

REPO = Path(__file__).resolve().parents[1]
FIXTURES = Path(os.environ.get("OCTO_REFERENCE_FIXTURES", REPO.parent / "shared" / "fixtures" / "octo-reference"))


@pytest.fixture(scope="session")
def fixtures_dir() -> Path:
    if not (FIXTURES / "README.md").exists():
        raise FileNotFoundError(
            f"reference fixtures not found at {FIXTURES}; place ../shared next to the repo or set OCTO_REFERENCE_FIXTURES"
        )
    return FIXTURES


# The quick subset for the edit-test loop is `pytest -m "not slow"` (under 3 minutes on 2 cores; CI runs everything).
# Besides the tests marked @pytest.mark.slow in their files, these node-id prefixes are slow: the longest tests by
# measured duration (pytest --durations), chosen so the subset still holds at least one test of every stage (and
# tests/test_layout.py imports every module). QUICK lists exceptions to a prefix.
SLOW = (
    "tests/test_reference_pipeline.py::test_tiny_diffusion_training",
    "tests/test_parallel.py::test_regress_with_two_workers",
    "tests/test_parallel.py::test_a_worker_killed",
    "tests/test_parallel.py::test_two_worker_processes",
    "tests/test_parallel.py::test_a_policy_error",
    "tests/test_parallel.py::test_an_episode_gets_the_same_bits",
    "tests/test_compare_baseline.py::",
    "tests/test_compare_e2e.py::",
    "tests/test_report_e2e.py::",
    "tests/test_run_resume.py::",
    "tests/test_run_checks.py::test_different_protocol_refuses",
    "tests/test_run_checks.py::test_language_model_with_goal_images",
    "tests/test_attribution.py::test_octo_step_function",
    "tests/test_attribution.py::test_deletion_drops",
    "tests/test_replay.py::test_intervention_runs_replay",
    "tests/test_replay.py::test_replay_is_equivalent_under_another",
    "tests/test_replay.py::test_a_candidate_with_one_weight",
    "tests/test_rollout_e2e.py::test_episode_writes_png",
    "tests/test_rollout_e2e.py::test_saved_attention_has_every_step",
    "tests/test_rollout_e2e.py::test_same_seed_gives_identical",
    "tests/test_rollout_e2e.py::test_different_seed_gives",
    "tests/test_rollout_e2e.py::test_goal_conditioned",
    "tests/test_loose_ends.py::test_copied_run_folder",
    "tests/test_tokenizer_choice.py::test_cli_offline",
    "tests/test_hold_gripper.py::test_six_d",
    "tests/test_octo_api.py::test_readout_rows_sum_to_one_and_equal_full_matrix_rows",
    "tests/test_octo_api.py::test_bounds_unnormalisation",
    "tests/test_octo_api.py::test_random_model_from_a_checkpoint",
    "tests/test_octo_api.py::test_no_recompilation",
    "tests/test_octo_equivalence.py::test_sampled_actions_with_prngkey0[tiny_goal]",
    "tests/test_octo_equivalence.py::test_sampled_actions_other_threefry",
    "tests/test_envs_sim.py::test_vector_env",
    "tests/test_envs_sim.py::test_env_checker",
    "tests/test_envs_sim.py::test_every_registered_task_resets_and_steps[",
    "tests/test_interventions.py::test_mask_top",
    "tests/test_finetune_e2e.py::test_octo_1_0",
    "tests/test_finetune_e2e.py::test_finetuned_checkpoint_runs",
)
QUICK = {"tests/test_envs_sim.py::test_every_registered_task_resets_and_steps[Lift]"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.nodeid.startswith(SLOW) and item.nodeid not in QUICK:
            item.add_marker(pytest.mark.slow)

#!/usr/bin/env bash
# Rebuild the LIBERO-Object reference policy in models/octo-reference-libero-object with fixed seeds (docs/libero.md,
# its model card): the scripted LIBERO-Object expert's demonstrations from sampled placements (never the 50 stored
# evaluation states; data/libero_object_demos/, not committed), then behaviour cloning on the CPU, warm-started from
# models/octo-reference-robosuite. Makes .venv and .venv-libero first when missing.
# Extra arguments go to `python -m reference_policies.libero_pipeline` (--recipe, --episodes, --steps, --out, --data,
# --workers, --init-from, --learning-rate, --seed, --task-weights, --close-below-top, --demonstrator-radii,
# --missed-grasps, --swaps, --dagger-episodes, --dagger-tasks, --dagger-close-below-top, --dagger-steps, --dagger-rounds,
# --dagger-retrain) and override its defaults.
source "$(dirname "$0")/_bootstrap.sh"
bash "$(dirname "$0")/setup_libero.sh"
export MUJOCO_GL="${MUJOCO_GL:-egl}" HF_HUB_OFFLINE=1
exec .venv/bin/python -m reference_policies.libero_pipeline "$@"

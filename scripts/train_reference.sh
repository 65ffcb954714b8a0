#!/usr/bin/env bash
# Rebuild the reference policy in models/octo-reference-robosuite with fixed seeds: scripted-expert demonstrations
# (data/reference_demos/, not committed; primary camera 128 px, wrist 64 px), then 6000 training steps on the CPU,
# warm-started from the committed 4x4-grid policy models/octo-reference-robosuite-64px (its transformer, heads, stems
# and T5 copied; the primary camera's position embeddings resampled from 4x4 to 8x8 patches).
# Measured on this 2-core CPU: recording at most 1701 s (PickPlaceCan alone 475 s) + training 1995 s: <= 62 min.
# PickPlaceCan's expert carries the can to a point 4 cm nearer the robot than its bin's centre (ExpertConfig.bin_inset),
# inside the arm's reach; the model card says why that moved PickPlaceCan from 40% to 68% on held-out seeds.
# Extra arguments go to `python -m reference_policies.pipeline` (--episodes, --steps, --out, --data, --workers,
# --init-from, --learning-rate, --dagger-episodes ...); they override these defaults. `--dagger-episodes 64` adds a
# DAgger round (PickPlaceCan corrections labelled by the state-based expert, then fine-tuning); it did not raise
# PickPlaceCan's success on validation seeds (the model card has the numbers), so the committed policy has none.
source "$(dirname "$0")/_bootstrap.sh"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
exec .venv/bin/python -m reference_policies.pipeline --init-from models/octo-reference-robosuite-64px "$@"

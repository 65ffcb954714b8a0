#!/usr/bin/env bash
# The GPU figure of region reliance's cost (issue 45): bench_reliance.py on inputs recorded on a machine with the
# simulator (`--save-inputs`), replayed on a GPU machine without it. Usage, from the repository root:
#   bash benchmarks/gpu_reliance.sh DIR   # DIR holds reliance_inputs_reference.pkl and reliance_inputs_small.pkl
# Uses .venv/bin/python when present, else python3; prints the environment it found first. WHEELS=DIR: install the
# wheels there first (pip download them here: gymnasium, huggingface_hub, tokenizers and their pure-Python needs).
set -u
DIR="${1:-data/bench}"
PY=.venv/bin/python; [ -x "$PY" ] || PY=python3
export HF_HUB_OFFLINE=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if [ -d "${WHEELS:-}" ]; then  # the harness's pure-Python needs the machine lacks (no network there): wheels carried
  "$PY" -m pip install -q --no-index --no-deps --target /tmp/octo-extra "$WHEELS"/*.whl && export PYTHONPATH="$PYTHONPATH:/tmp/octo-extra"
fi
nvidia-smi -L 2>&1 | head -2
"$PY" -c "import sys, jax, flax, numpy; print(sys.version.split()[0], 'jax', jax.__version__, 'flax', flax.__version__, 'numpy', numpy.__version__, jax.devices())" || exit 3
"$PY" benchmarks/bench_reliance.py --inputs "$DIR/reliance_inputs_reference.pkl" --reps 5
"$PY" benchmarks/bench_reliance.py --model random:octo-small-1.5 --inputs "$DIR/reliance_inputs_small.pkl" --reps 5

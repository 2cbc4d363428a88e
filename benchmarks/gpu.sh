#!/usr/bin/env bash
# The GPU benchmarks: nearest-hit engines ("jax" and "warp" on CUDA, beside single-threaded Embree
# on the host) and the filter step at the paper's scale (960x540, 2500 particles, strides 20/8/4)
# with both engines. Writes benchmarks/results/*_gpu_<engine>.md.
#
# Set-up on a fresh CUDA 12 machine (from the repository root):
#   python3 -m venv .venv && .venv/bin/python -m pip install -e ".[gpu,bench]" "jax[cuda12]!=0.10.2"
# then:
#   bash benchmarks/gpu.sh            # FRAMES=3 by default
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
FRAMES=${FRAMES:-3}
OUT=benchmarks/results
"$PYTHON" - <<'PY'
import jax
assert jax.default_backend() == "gpu", f"no GPU backend: {jax.devices()}"
print(jax.devices())
PY
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu_device.txt"
"$PYTHON" benchmarks/engines.py --engines jax,warp,auto | tee "$OUT/engines_gpu.md"
for engine in warp jax; do
  "$PYTHON" benchmarks/filter_step.py --engine "$engine" --frames "$FRAMES" --cases stride \
    | tee "$OUT/filter_step_gpu_$engine.md"
done
"$PYTHON" benchmarks/filter_profile.py --engine warp | tee "$OUT/filter_profile_gpu_warp.md"

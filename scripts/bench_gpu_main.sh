#!/usr/bin/env bash
# The product's own command on one NVIDIA GPU (docs/benchmarks.md §9c): the default main job on the
# embedded bedroom with the shipped model, cold (no compilation or estimate cache), then the same run
# with the prior in bfloat16, then 1000 steps instead of 100 (the cosine schedule stretched to them),
# each to its end (outputs, scores, metrics.json) if the budget allows. On a machine whose Python has jax with CUDA and this package's other needs
# (trimesh, OpenImageIO, embreex, xatlas, matplotlib) on its path:
#
#     PYTHONPATH=$PWD bash scripts/bench_gpu_main.sh OUT_DIR [WORK_DIR] [SECONDS]
#
# Each run starts from an empty cache and output folder. A run starts only if at least 60 s of SECONDS
# (default 540) are left, and is stopped at the budget: on an H200 the first two take about 3 min
# each, so the 1000-step run needs SECONDS of about 700 to finish (at 515 it is stopped in its scoring).
# Everything lands in OUT_DIR: gpu.txt (card, versions, XLA_FLAGS), NAME.log (the log's last 120
# lines) and NAME.metrics.json for NAME in cold, bf16, steps1000.
set -uo pipefail
out=${1:?usage: bench_gpu_main.sh OUT_DIR [WORK_DIR] [SECONDS]}
work=${2:-${TMPDIR:-/tmp}/jaxdistill-gpu-main}
budget=${3:-540}
start=$SECONDS
mkdir -p "$out" "$work"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv | tee "$out/gpu.txt"
python3 - <<'PY' 2>&1 | tee -a "$out/gpu.txt"
import os
import jaxdistill  # noqa: F401  (sets the package's XLA flag before JAX starts)
import jax, flax, optax, numpy
print("jax", jax.__version__, "flax", flax.__version__, "optax", optax.__version__, "numpy", numpy.__version__)
print("devices", jax.devices())
print("XLA_FLAGS", os.environ.get("XLA_FLAGS"))
print("a sum on the device:", float(jax.numpy.arange(4.0).sum()))
PY

run() {   # NAME, then the main job's extra flags
  local name=$1 t0=$SECONDS left
  shift
  left=$((budget - (SECONDS - start)))
  if [ "$left" -lt 60 ]; then echo "$name: not run (${left} s left)" | tee -a "$out/gpu.txt"; return; fi
  rm -rf "${work:?}/cache_$name" "${work:?}/$name"
  JAXDISTILL_CACHE="$work/cache_$name" timeout "$left" python3 -m jaxdistill.main \
    --flagfile=configs/bedroom.cfg --out_dir="$work/$name" "$@" 2>&1 | tr '\r' '\n' | tail -120 > "$out/$name.log"
  echo "$name: exit ${PIPESTATUS[0]} after $((SECONDS - t0)) s" | tee -a "$out/gpu.txt"
  cp "$work/$name/metrics.json" "$out/$name.metrics.json" 2>/dev/null || true
}
run cold
run bf16 --prior_dtype=bfloat16
run steps1000 --steps=1000 --eval_every=250 --ckpt_every=500 --log_every=50
echo "done at $((SECONDS - start)) s" | tee -a "$out/gpu.txt"

#!/usr/bin/env bash
# docs/benchmarks.md §9, the UNet's share of the card: the thesis's setting (512x384 renders, 5 maps,
# pages up to 4096^2, random full-size RGB<->X weights, bfloat16) with XLA's chunked attention and with
# cuDNN's fused attention (`--dtypes=bfloat16,bfloat16_cudnn`), at 1 and at 4 views a step (a UNet
# batch of 5 and of 20), on one NVIDIA GPU whose Python has jax with CUDA, torch, diffusers, trimesh,
# OpenImageIO, embreex and xatlas. The 1-view leg takes about 6 minutes on an H200 (weights, then two
# workers of ~150 s), the 4-view leg about 5 more; a leg is skipped when fewer than 330 s of SECONDS
# (default 900) are left, so a shorter budget measures the 1-view pair alone:
#
#     PYTHONPATH=$PWD bash scripts/bench_gpu_unet.sh OUT_DIR [WORK_DIR] [SECONDS]
#
# First it checks the fused attention against the chunked one at the UNet's shapes (bf16, both
# against a float32 reference), so a wrong kernel is seen before it is timed. Everything lands in
# OUT_DIR: gpu.txt, attention_check.txt, bench_vps1.log / .json, bench_vps4.log / .json.
set -uo pipefail
out=${1:?usage: bench_gpu_unet.sh OUT_DIR [WORK_DIR] [SECONDS]}
work=${2:-${TMPDIR:-/tmp}/jaxdistill-gpu}
budget=${3:-900}
start=$SECONDS
mkdir -p "$out" "$work"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv | tee "$out/gpu.txt"
python3 - <<'PY' 2>&1 | tee "$out/attention_check.txt"
import jax, jax.numpy as jnp, numpy as np
from jaxdistill.models import layers
print("jax", jax.__version__, jax.devices())
rng = np.random.default_rng(0)
for name, nk in (("self", 3072), ("cross", 77)):      # 64x48 latent tokens; 77 prompt tokens
    q = rng.standard_normal((5, 3072, 320)).astype(np.float32)
    k, v = (rng.standard_normal((5, nk, 320)).astype(np.float32) for _ in range(2))
    ref = np.asarray(jax.jit(lambda a, b, c: layers.dot_product_attention(a, b, c, 5, precision="highest"))(q, k, v))
    b16 = [jnp.asarray(x, jnp.bfloat16) for x in (q, k, v)]
    for label, chunk in (("chunked", layers.DEFAULT_ATTENTION_CHUNK), ("cudnn", layers.FUSED_CUDNN)):
        got = np.asarray(jax.jit(lambda a, b, c: layers.dot_product_attention(a, b, c, 5, chunk_size=chunk))(*b16),
                         np.float32)
        print(f"{name:5s} attention, bf16 {label:8s}: max |err| / max |ref| = "
              f"{np.abs(got - ref).max() / np.abs(ref).max():.2e}")
PY
if [ ! -f "$work/rgb-to-x/unet/diffusion_pytorch_model.safetensors" ]; then
  python3 scripts/make_random_rgbx.py --size=full --out="$work/rgb-to-x" 2>&1 | tail -2
fi
echo "weights ready at $((SECONDS - start)) s"
for vps in 1 4; do
  left=$((budget - (SECONDS - start) - 10))
  [ "$left" -gt 330 ] || { echo "no time left for $vps views a step (${left} s; a leg takes about 300)"; break; }
  timeout "$left" python3 scripts/bench_step.py --rgbx_dir="$work/rgb-to-x" --render_sizes=512 --map_counts=5 \
    --frameworks=jax --dtypes=bfloat16,bfloat16_cudnn --views_per_step=$vps --max_texture_size=4096 \
    --repeats=5 --last_stage=unet --stage_cases=last --fragment_cache="$work/fragments" \
    --convert_cache="$work/convert" --json 2>&1 | grep -v "view/s\]" | tee "$out/bench_vps$vps.log"
  tail -1 "$out/bench_vps$vps.log" | grep '^{' > "$out/bench_vps$vps.json" || true
  echo "$vps views a step done at $((SECONDS - start)) s"
done

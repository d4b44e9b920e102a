#!/usr/bin/env bash
# The GPU table of docs/benchmarks.md (§9) in one command, on a machine with one NVIDIA GPU whose
# Python already has jax with CUDA, torch with CUDA, transformers and this package's other needs
# (diffusers, trimesh, OpenImageIO, embreex, xatlas) on its path:
#
#     PYTHONPATH=$PWD bash scripts/bench_gpu.sh OUT_DIR [WORK_DIR] [SECONDS]
#
# 1. random weights of the real RGB<->X architecture (scripts/make_random_rgbx.py --size=full,
#    4.8 GB in WORK_DIR, default $TMPDIR/jaxdistill-gpu): no licensed weights are needed for timings;
# 2. scripts/bench_step.py at the thesis's setting: 512-pixel renders (the bedroom is 4:3, so
#    512x384), textures up to 4096^2, 1 and 5 maps, our step in float32 and bfloat16 against the
#    thesis's PyTorch recipe on the same GPU, with peak GPU memory, compile time and the UNet's share
#    of the card's bf16 peak; the PyTorch recipe runs first, so a time limit cuts ours last;
# 3. with the time left of SECONDS (default 540), `python -m jaxdistill.main --flagfile=configs/thesis.cfg`
#    on the same weights for a few hundred steps: its log's steps per second give the thesis run's time.
# Everything lands in OUT_DIR: gpu.txt, versions.txt, bench_step.log (the table is its end),
# bench_step.json, thesis.log.
set -uo pipefail
out=${1:?usage: bench_gpu.sh OUT_DIR [WORK_DIR] [SECONDS]}
work=${2:-${TMPDIR:-/tmp}/jaxdistill-gpu}
budget=${3:-540}
start=$SECONDS
mkdir -p "$out" "$work"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv | tee "$out/gpu.txt"
python3 - <<'PY' 2>&1 | tee "$out/versions.txt"
import jax, flax, optax, torch, diffusers, transformers
print("jax", jax.__version__, jax.default_backend(), jax.devices())
print("flax", flax.__version__, "optax", optax.__version__, "torch", torch.__version__,
      torch.cuda.is_available(), "diffusers", diffusers.__version__, "transformers", transformers.__version__)
PY
python3 -c "import jaxdistill.engine.loop, jaxdistill.engine.problem, jaxdistill.models.prior, diffusers, trimesh, OpenImageIO, embreex" \
  || { echo "the package does not import with this Python's packages; nothing measured"; exit 1; }
if [ ! -f "$work/rgb-to-x/unet/diffusion_pytorch_model.safetensors" ]; then
  python3 scripts/make_random_rgbx.py --size=full --out="$work/rgb-to-x" 2>&1 | tail -3
fi
echo "weights ready at $((SECONDS - start)) s"
left=$((budget - (SECONDS - start) - 30))
timeout "$left" python3 scripts/bench_step.py --rgbx_dir="$work/rgb-to-x" --render_sizes=512 --map_counts=1,5 \
  --frameworks=torch,jax --dtypes=bfloat16,float32 --torch_device=cuda --max_texture_size=4096 --repeats=5 \
  --last_stage=unet --stage_cases=last --fragment_cache="$work/fragments" --convert_cache="$work/convert" \
  --json 2>&1 | grep -v "view/s\]" | tee "$out/bench_step.log"
tail -1 "$out/bench_step.log" | grep '^{' > "$out/bench_step.json" || true
echo "bench done at $((SECONDS - start)) s"
left=$((budget - (SECONDS - start) - 10))
if [ "$left" -gt 90 ]; then
  timeout "$left" python3 -m jaxdistill.main --flagfile=configs/thesis.cfg --rgbx_dir="$work/rgb-to-x" \
    --convert_cache="$work/convert" --out_dir="$work/thesis" --steps=300 --estimate_steps=1 \
    --log_every=25 2>&1 | tr '\r' '\n' | grep -v "view/s\]" | tail -60 > "$out/thesis.log"
  echo "thesis run ended at $((SECONDS - start)) s (exit ${PIPESTATUS[0]})"
fi

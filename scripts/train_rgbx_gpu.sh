#!/usr/bin/env bash
# The UNet of our RGB<->X-family model v2, trained on one NVIDIA GPU for about MINUTES, from
# latents encoded beforehand by the shipped model's VAE; exported where torch is, and shipped only
# if it beats the shipped model on the validation rooms (docs/benchmarks.md §9d).
#
#     # where the shards are (2 CPU cores are enough; 8-bit latents, about 5 KB an image):
#     python scripts/train_rgbx.py --data=data/rgbx/train --work=data/rgbx_v2 \
#         --init=jaxdistill/models/rgbx_rooms --latent_bits=8 --stage=latents
#     # on the GPU machine, whose Python has jax with CUDA, flax, optax, orbax-checkpoint and tqdm:
#     PYTHONPATH=$PWD bash scripts/train_rgbx_gpu.sh data/rgbx_v2/latents.npz OUT_DIR [MINUTES] [WORK_DIR] [CANDIDATES]
#     # back where torch is, for the candidate chosen (X = a, b or c, with its flags below):
#     mkdir -p data/rgbx_v2_X && cp OUT_DIR/unet_ema_X.npz data/rgbx_v2_X/unet_ema.npz \
#         && cp data/rgbx_v2/latents.npz data/rgbx_v2_X/ \
#         && python -c "import json; print(json.dumps(json.load(open('OUT_DIR/runs.json'))['X']['steps']))" \
#            > data/rgbx_v2_X/unet_steps.json
#     python scripts/train_rgbx.py --data=data/rgbx/train --work=data/rgbx_v2_X \
#         --init=jaxdistill/models/rgbx_rooms --fresh_unet --latent_bits=8 --stage=export FLAGS_X ...
#
# CANDIDATES (default a; several, e.g. abc, train at once on the one card):
#   a: blocks 32,64,64,64, 1 layer each (v1's UNet: the same cost in the main job)
#   b: blocks 32,64,64,64, 2 layers each
#   c: blocks 48,96,96,96, 1 layer each
# Measured on an H200 (§9d): the three at once took 73-125 ms a step after 3-4 minutes of
# compilation, so none fitted 6.5 minutes; a alone took about 60 ms a step (batch 256) after about
# 80 s. So one candidate fits a 15-minute lease (about 8 minutes: 6,000-7,000 steps).
# MINUTES (default 6): each candidate's --unet_minutes (steps chosen by its own measured speed,
# kept in unet_steps_X.json); "steps:N" trains N steps instead (a quick check of this script).
# OUT_DIR gets train.log (the card, the versions, the three logs' ends), unet_ema_X.npz (the final EMA weights,
# float16: what the float16 export ships), unet_ema_X_half.npz (the EMA weights at the checkpoint
# nearest half the steps, to tell on the validation rooms whether the second half paid) and
# runs.json ({X: {flags, steps (unet_steps.json), half (that checkpoint's step), loss (the loss log)}}).
set -uo pipefail
latents=${1:?usage: train_rgbx_gpu.sh LATENTS OUT_DIR [MINUTES] [WORK_DIR]}
out=${2:?usage: train_rgbx_gpu.sh LATENTS OUT_DIR [MINUTES] [WORK_DIR]}
minutes=${3:-6}
work=${4:-${TMPDIR:-/tmp}/jaxdistill-rgbx-v2}
candidates=$(echo "${5:-a}" | grep -o '[abc]' | tr '\n' ' ')
mkdir -p "$out" "$work"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$out/gpu.txt" 2>&1 || true
python3 -c "import jax, flax, optax; print('jax', jax.__version__, jax.devices(), 'flax', flax.__version__, 'optax', optax.__version__)" \
  2>&1 | tee -a "$out/gpu.txt"
case "$minutes" in
  steps:*) length="--unet_steps=${minutes#steps:}" ;;
  # a backstop a minute later: a slower step than the one timed stops with a checkpoint and its
  # EMA snapshot, which is then what comes back
  *) length="--unet_minutes=$minutes --time_limit=$(python3 -c "print($minutes + 1)")" ;;
esac
declare -A flags=([a]="--unet_blocks=32,64,64,64 --unet_layers_per_block=1"
                  [b]="--unet_blocks=32,64,64,64 --unet_layers_per_block=2"
                  [c]="--unet_blocks=48,96,96,96 --unet_layers_per_block=1")
for x in $candidates; do
  mkdir -p "$work/$x" && cp "$latents" "$work/$x/latents.npz"
  # the processes share the card: each may take a quarter of its memory
  XLA_PYTHON_CLIENT_MEM_FRACTION=0.25 python3 scripts/train_rgbx.py --data=data/rgbx/train --work="$work/$x" \
    --init=jaxdistill/models/rgbx_rooms --fresh_unet --latent_bits=8 --stage=unet --unet_batch=256 \
    --ckpt_every=10000 --ema_snapshots $length ${flags[$x]} > "$out/train_$x.log" 2>&1 &
done
wait
for x in $candidates; do
  echo "== $x: ${flags[$x]}"
  tr '\r' '\n' < "$out/train_$x.log" | grep -v "step/s\]$" | tail -15
  rm "$out/train_$x.log"
  if [ ! -f "$work/$x/unet_ema.npz" ]; then
    last=$(python3 -c "import sys, pathlib; f = sorted(pathlib.Path(sys.argv[1]).glob('unet_ema_*.npz'), key=lambda p: int(p.stem.split('_')[-1])); print(f[-1] if f else '')" "$work/$x")
    [ -n "$last" ] || continue
    echo "stopped early: the newest snapshot, $last, comes back as unet_ema_$x.npz"
    cp "$last" "$work/$x/unet_ema.npz"
  fi
  half=$(python3 -c "import json, sys; s = json.load(open(sys.argv[1]))['steps'] // 2; print(round(s / 10000) * 10000)" "$work/$x/unet_steps.json" 2>/dev/null)
  for pair in "unet_ema.npz:unet_ema_$x.npz" "unet_ema_$half.npz:unet_ema_${x}_half.npz"; do
    [ -f "$work/$x/${pair%%:*}" ] && python3 -c "import numpy as np, sys; z = np.load(sys.argv[1]); np.savez(sys.argv[2], **{k: z[k].astype(np.float16) for k in z.files})" \
      "$work/$x/${pair%%:*}" "$out/${pair#*:}"
  done
  echo "half: step $half"
done > "$out/train.log" 2>&1
cat "$out/gpu.txt" "$out/train.log" > "$out/train.all" && mv "$out/train.all" "$out/train.log" && rm "$out/gpu.txt"
cat "$out/train.log"
python3 - "$work" "$out/runs.json" "${flags[a]}" "${flags[b]}" "${flags[c]}" <<'PY'
import json, sys
from pathlib import Path
work, runs = Path(sys.argv[1]), {}
for x, flags in zip("abc", sys.argv[3:]):
    steps, loss = work / x / "unet_steps.json", work / x / "unet_loss.jsonl"
    chosen = json.loads(steps.read_text()) if steps.is_file() else None
    runs[x] = {"flags": flags, "steps": chosen, "half": round(chosen["steps"] // 2 / 10000) * 10000 if chosen else None,
               "loss": [json.loads(line) for line in loss.read_text().splitlines()] if loss.is_file() else []}
Path(sys.argv[2]).write_text(json.dumps(runs, indent=1))
PY
ls -la "$out"

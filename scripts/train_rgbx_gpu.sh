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
#     # back where torch is, for the candidate chosen (X = a, b or c, with its flags below; with
#     # MINUTES given as steps:N there is no steps record: pass --unet_steps=N to the export instead):
#     mkdir -p data/rgbx_v2_X && cp OUT_DIR/unet_ema_X.npz data/rgbx_v2_X/unet_ema.npz \
#         && cp data/rgbx_v2/latents.npz data/rgbx_v2_X/ \
#         && python -c "import json; r = json.load(open('OUT_DIR/runs.json'))['X']; print(json.dumps(r['steps']))" \
#            > data/rgbx_v2_X/unet_steps.json \
#         && python -c "import json; [print(json.dumps(l)) for l in json.load(open('OUT_DIR/runs.json'))['X']['loss']]" \
#            > data/rgbx_v2_X/unet_loss.jsonl         # the model record's final loss
#     python scripts/train_rgbx.py --data=data/rgbx/train --work=data/rgbx_v2_X \
#         --init=jaxdistill/models/rgbx_rooms --fresh_unet --latent_bits=8 --stage=export --unet_batch=256 FLAGS_X
#
# CANDIDATES (default a; several, e.g. abc, train at once on the one card):
#   a: blocks 32,64,64,64, 1 layer each (v1's UNet: the same cost in the main job)
#   b: blocks 32,64,64,64, 2 layers each
#   c: blocks 48,96,96,96, 1 layer each
# Measured on an H200 (docs/benchmarks.md §9d): the three at once took 73-125 ms a step after 3-4
# minutes of compiling, so none fitted 6.5 minutes; a alone took about 60 ms a step (batch 256)
# after about 80 s. So one candidate fits a 15-minute lease: MINUTES=8 gives about 5,000 steps
# (--unet_minutes counts both compilations and the probe).
# MINUTES (default 6): each candidate's --unet_minutes (steps chosen by its own measured speed,
# kept in unet_steps_X.json); "steps:N" trains N steps instead (a quick check of this script).
# OUT_DIR gets train.log (the card, the versions, the logs' ends), unet_ema_X.npz (the final EMA
# weights, float16: what the float16 export ships), unet_ema_X_half.npz (the EMA weights at the
# checkpoint nearest half the steps, every 1,000: to tell on the validation rooms whether the second
# half paid) and runs.json ({X: {flags, steps (unet_steps.json), half (that checkpoint's step),
# loss (the loss log)}}).
set -uo pipefail
usage="usage: train_rgbx_gpu.sh LATENTS OUT_DIR [MINUTES] [WORK_DIR] [CANDIDATES]"
latents=${1:?$usage}
out=${2:?$usage}
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
  # a backstop (the process's whole time, a minute and a half more): a slower step than the one
  # timed stops with a checkpoint and its EMA snapshot, which is then what comes back
  *) length="--unet_minutes=$minutes --time_limit=$(python3 -c "print($minutes + 1.5)")" ;;
esac
declare -A flags=([a]="--unet_blocks=32,64,64,64 --unet_layers_per_block=1"
                  [b]="--unet_blocks=32,64,64,64 --unet_layers_per_block=2"
                  [c]="--unet_blocks=48,96,96,96 --unet_layers_per_block=1")
for x in $candidates; do
  rm -rf "${work:?}/$x" && mkdir -p "$work/$x" && cp "$latents" "$work/$x/latents.npz"   # nothing stale
  # the processes share the card: each may take a quarter of its memory
  XLA_PYTHON_CLIENT_MEM_FRACTION=0.25 python3 scripts/train_rgbx.py --data=data/rgbx/train --work="$work/$x" \
    --init=jaxdistill/models/rgbx_rooms --fresh_unet --latent_bits=8 --stage=unet --unet_batch=256 \
    --ckpt_every=1000 --ema_snapshots $length ${flags[$x]} > "$out/train_$x.log" 2>&1 &
done
wait
for x in $candidates; do
  echo "== $x: ${flags[$x]}"
  tr '\r' '\n' < "$out/train_$x.log" | grep -v "step/s\]$" | tail -15
  rm "$out/train_$x.log"
  # the EMA snapshots (unet_ema_<step>.npz, every checkpoint): the newest stands in for a run the
  # backstop stopped; the one nearest half the steps comes back beside the final weights
  read -r newest half <<<"$(python3 - "$work/$x" <<'PY'
import json, pathlib, sys
work = pathlib.Path(sys.argv[1])
snaps = sorted((int(p.stem.rsplit("_", 1)[1]), p) for p in work.glob("unet_ema_*.npz") if p.stem.rsplit("_", 1)[1].isdigit())
record = work / "unet_steps.json"
steps = json.loads(record.read_text())["steps"] if record.is_file() else (snaps[-1][0] if snaps else 0)
middle = [p for s, p in snaps if s < steps]
half = min(middle, key=lambda p: abs(int(p.stem.rsplit("_", 1)[1]) - steps / 2)) if middle else ""
print(snaps[-1][1] if snaps else "", half)
PY
)"
  if [ ! -f "$work/$x/unet_ema.npz" ]; then
    [ -n "$newest" ] || continue
    echo "stopped early: the newest snapshot, $newest, comes back as unet_ema_$x.npz"
    cp "$newest" "$work/$x/unet_ema.npz"
  fi
  for pair in "$work/$x/unet_ema.npz:unet_ema_$x.npz" "$half:unet_ema_${x}_half.npz"; do
    [ -f "${pair%%:*}" ] && python3 -c "import numpy as np, sys; z = np.load(sys.argv[1]); np.savez(sys.argv[2], **{k: z[k].astype(np.float16) for k in z.files})" \
      "${pair%%:*}" "$out/${pair#*:}"
  done
  echo "half-way snapshot: ${half:-none}"
  basename "${half:-}" .npz | sed -n 's/^unet_ema_\([0-9]*\)$/\1/p' > "$work/$x/half_step"
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
    half = (work / x / "half_step").read_text().strip() if (work / x / "half_step").is_file() else ""
    runs[x] = {"flags": flags, "steps": chosen, "half": int(half) if half else None,
               "loss": [json.loads(line) for line in loss.read_text().splitlines()] if loss.is_file() else []}
Path(sys.argv[2]).write_text(json.dumps(runs, indent=1))
PY
ls -la "$out"

#!/usr/bin/env bash
# One training run on a GPU machine, prepared to fit one 10-minute remote call
# (leave ~2 minutes for start-up, validation and the copy back).
#
# There, python3 already holds PyTorch, numpy, scipy, OpenCV, safetensors, matplotlib and tqdm. Training needs
# nothing else: no ROS, gtsam or bags (test_train.py checks that). The synthetic renderer feeds the GPU from the
# CPU cores. The shared development data does not travel, so this trains on rendered rooms only.
#
#   remote command:  bash scripts/device_train.sh paper 7      # preset, minutes of training
#   CPU dry run:     OUT=/tmp/dev DEVICE=cpu SIZE=64x48 BATCH=1 WORKERS=1 bash scripts/device_train.sh lite 0.3
#
# Comes back under $OUT (at most 8 files of < 16 MiB, what such a call returns):
#   <preset>.safetensors.partNN   the exported best weights, split
#                                 join them: cat <files_at>/<preset>.safetensors.part* > dpv_sensor/weights/<preset>.safetensors
#   log.txt, train.jsonl, val.jsonl, loss_curves.png, val_montage_latest.png
# Score the result here: python -m dpv_sensor.benchmarks.heldout / benchmarks.calibration (README).
set -uo pipefail
preset=${1:-paper}
minutes=${2:-7}
out=${OUT:?OUT must name the folder for the results (the remote runner sets it)}
device=${DEVICE:-cuda}
size=${SIZE:-256x192}
batch=${BATCH:-8}
workers=${WORKERS:-12}
run=/tmp/dpv_train_${preset}
mkdir -p "$out"
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
py=$(command -v python3)
[ -x .venv/bin/python ] && [ "$device" = cpu ] && py=.venv/bin/python
init=()
[ "$preset" = lite ] && init=(--init-weights dpv_sensor/weights/lite.safetensors)
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee "$out/log.txt"
"$py" -m dpv_sensor.tools.train --preset "$preset" --run-dir "$run" --export "$run/$preset.safetensors" \
    "${init[@]}" --device "$device" --amp auto --width "${size%x*}" --height "${size#*x}" --batch-size "$batch" \
    --unroll 4 --startup-prob 0.3 --pose-noise-prob 0.3 --steps 4000 --lr 5e-4 --warmup 200 \
    --num-workers "$workers" --threads 4 --val-every 500 --ckpt-every 500 --val-seeds 0-7 --val-keyframes 14 \
    --val-pose-noise 0.03 0.5 --select-metric abs_rel_knet_both \
    --max-minutes "$minutes" --quiet 2>&1 | tee -a "$out/log.txt"
status=${PIPESTATUS[0]}
if [ -f "$run/$preset.safetensors" ]; then
    split -b 15M -d "$run/$preset.safetensors" "$out/$preset.safetensors.part"
fi
for f in train.jsonl val.jsonl loss_curves.png val_montage_latest.png; do
    [ -f "$run/$f" ] && cp "$run/$f" "$out/"
done
ls -l "$out"
exit "$status"

#!/usr/bin/env bash
# Continue the shipped model (the lineage's head) on a lent GPU in ONE device call (a task gets ~15 min of device time, starts included).
#
# Here, once:  python -m pipelines.studies.carry_pack --dataset kitti_unlabelled --root ../shared/data/kitti_unlabelled .carry/unl
#              (87 pairs as JPEG q95, ~33 MB: the PNGs and their labels are too big to carry)
# Device:      run(command="bash pipelines/studies/gpu/continue.sh", carry=[".carry/unl"], timeout_s=600)
# Here, after: mkdir -p out/pretrained/NAME && cp FILES_AT/NAME.safetensors out/pretrained/NAME/model.safetensors
#              python -m pipelines.studies.train_pretrained eval NAME   (CPU, float32, the lineage's rule: RESULTS.md)
#
# On the device it labels the pack with PVM (all cores, lzf shards: no hdf5plugin there), times 20 steps, sizes the
# run to BUDGET_S seconds and trains it: the lineage's loss (L_P confidence-weighted + 0.1 L_R + 0.1 L_S, no L_T)
# from INIT with one OneCycle (peak 1e-4), bf16, batch 8, 320x960 crops enlarged by U(SCALE_RANGE), N_s = 8.
# NAME.safetensors, its metrics.jsonl, config.yaml and env.txt land in $OUT. The trained-on images are JPEG-decoded; its report says so.
# A CPU smoke run of the same logic: DEVICE=cpu AMP=none BATCH=1 CROP=64x128 ITERS=1 BUDGET_S=1 PROBE=4 WORKERS=1 THREADS=2
set -euo pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
INIT=${INIT:-pretrained}   # the shipped file (version 9: it runs at input scale 1.625, so it trains on enlarged crops)
SCALE_RANGE=${SCALE_RANGE:-1.5,1.75}  # version 9's scale augmentation (the export records 1.625); 1.0,1.0 = off
NAME=${NAME:-gpu_h}
PACK=${PACK:-.carry/unl}
BUDGET_S=${BUDGET_S:-360}   # training wall seconds after the probe
END_AT=${END_AT:-}          # epoch seconds by which training must end (overrides BUDGET_S): session.sh sets it
PROBE=${PROBE:-20}          # probe steps (the mean of the second half is the step time)
DEVICE=${DEVICE:-cuda} AMP=${AMP:-bf16} BATCH=${BATCH:-8} CROP=${CROP:-320x960} ITERS=${ITERS:-8}
SEED=${SEED:-30} JOBS=${JOBS:-$(nproc)} WORKERS=${WORKERS:-6} THREADS=${THREADS:-4}
W=${WORK:-/tmp/pv}
OUTD=${OUT:-/tmp/out}
PY=${PY:-python3}
mkdir -p "$W" "$OUTD"

{ date -u; git rev-parse --short HEAD 2>/dev/null || true; nproc
  command -v nvidia-smi > /dev/null && nvidia-smi -L
  $PY -c "import torch, numba, h5py, cv2; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(),
'numba', numba.__version__, 'h5py', h5py.__version__, 'cv2', cv2.__version__)"; } | tee "$W/env.txt"

if [ ! -e "$W/labels.ok" ]; then  # session.sh labels while the GPU tests run, then leaves this marker
  t0=$SECONDS
  $PY -m pvm_labeler.cli run --dataset folder --root "$PACK" --out "$W/labels" --jobs "$JOBS" --compression lzf \
    --quiet 2>&1 | tail -n 2
  echo "labels in $((SECONDS - t0)) s" | tee -a "$W/env.txt"
fi

train() {  # out dir, steps, extra args: the lineage's recipe at GPU size
  $PY -m optstereo.cli train --config pipelines/studies/recipes/cpu_main.yaml --init "$INIT" --lambda-t 0 --conf-weight \
    --labels "$W/labels" --out "$1" --steps "$2" --lr 1e-4 --seed "$SEED" --device "$DEVICE" --amp "$AMP" \
    --batch-size "$BATCH" --crop "$CROP" --iters "$ITERS" --workers "$WORKERS" --threads "$THREADS" \
    --scale-range "$SCALE_RANGE" --quiet "${@:3}"
}

rm -rf "$W/probe"
train "$W/probe" "$PROBE" --log-every 2 --ckpt-every 100000
step_s=$($PY - "$W/probe/metrics.jsonl" <<'EOF'
import json, sys
rows = [json.loads(line) for line in open(sys.argv[1])]
half = rows[len(rows) // 2:]
print(sum(r["step_time_s"] for r in half) / len(half))
EOF
)
if [ -n "$END_AT" ]; then BUDGET_S=$((END_AT - $(date +%s) - 25)); fi  # 25 s: start-up, export and copy
# 0.92: the run also loads data, checkpoints every 500 steps and exports; its OneCycle must end before the cap does
steps=$($PY -c "print(max(4, int(0.92 * $BUDGET_S / $step_s) // 50 * 50))")
echo "probe: $step_s s/step -> $steps steps" | tee -a "$W/env.txt"
echo "$(date -u +%FT%TZ) train $W/$NAME $steps (INIT=$INIT seed $SEED $DEVICE $AMP batch $BATCH crop $CROP N_s $ITERS)" \
  | tee -a "$W/env.txt"
train "$W/$NAME" "$steps" --ckpt-every 500 --max-minutes "$($PY -c "print(max($BUDGET_S, 1) / 60)")"

cp "$W/$NAME/model.safetensors" "$OUTD/$NAME.safetensors"  # the trainer exports it when the run ends
cp "$W/$NAME/metrics.jsonl" "$W/$NAME/config.yaml" "$W/env.txt" "$OUTD/"

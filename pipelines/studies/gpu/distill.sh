#!/usr/bin/env bash
# Issue 42 on a lent GPU, in ONE device call (a task gets ~15 min of device time, the machine's start included):
#   1. PVM labels of the distillation pack (all CPU cores, lzf shards), in the background, while
#   2. the teacher (version 14, `pretrained-accurate` since version 15 shipped: 3 passes at 1.625x, choice + jump limit, weighted median) writes both
#      views of every pair on the GPU (optstereo-distill maps, float32);
#   3. optstereo-distill fill: PVM labels + the teacher's left-right consistent views in PVM's holes (weight 0.5);
#   4. two students trained side by side on the GPU from those shards with the paper's losses (L_P confidence-
#      weighted + 0.1 L_R + 0.1 L_S), bf16, batch 8, 320x960 crops, flip-swap:
#        student  OptStereo from version 14's weights, ONE pass from zero at input scale 1, no filter (the default);
#        fast     PVM-HITNet from scratch (the fast model);
#   5. KITTI-size infer() times of both on CUDA (bf16 and float32, synchronised).
# Here, once: python -m pipelines.studies.gpu.distill_pack .carry/distill   (144 unlabelled pairs as JPEG, the quality
#   that fits the 64 MiB carry beside the tracked tree: ~35 MB)
# Device:     run(command="bash pipelines/studies/gpu/distill.sh", carry=[".carry/distill"], timeout_s=600)
# $OUT: session.log, student.safetensors, fast.safetensors, their metrics (*.jsonl), distill.json (label/fill
#       counts), cuda_times.json.
# CPU smoke run of the same logic: DEVICE=cpu AMP=none BATCH=1 CROP=64x128 ITERS=1 STUDENT_STEPS=2 FAST_STEPS=2
#   PACK=<small pack> TOTAL_S=100000 WORKERS=0 THREADS=1 bash pipelines/studies/gpu/distill.sh
set -uo pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
T0=$(date +%s)
TOTAL_S=${TOTAL_S:-530}         # everything ends by T0 + TOTAL_S (the call's limit is 600 s)
PACK=${PACK:-.carry/distill}
DEVICE=${DEVICE:-cuda} AMP=${AMP:-bf16} BATCH=${BATCH:-8} CROP=${CROP:-320x960} ITERS=${ITERS:-8}
STUDENT_STEPS=${STUDENT_STEPS:-2000} FAST_STEPS=${FAST_STEPS:-4000}
WORKERS=${WORKERS:-5} THREADS=${THREADS:-2} JOBS=${JOBS:-12}
W=${WORK:-/tmp/pv}
OUTD=${OUT:-/tmp/out}
PY=${PY:-python3}
mkdir -p "$OUTD" "$W"
exec > >(tee -a "$OUTD/session.log") 2>&1
elapsed() { echo "+$(( $(date +%s) - T0 )) s"; }
failed=()  # the stages that failed: the call exits non-zero when any did
echo "distill session start $(date -u +%FT%TZ), ends by +$TOTAL_S s"
{ git rev-parse --short HEAD 2>/dev/null; nproc; command -v nvidia-smi > /dev/null && nvidia-smi -L
  $PY -c "import torch, numba, h5py, cv2; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(),
'numba', numba.__version__, 'h5py', h5py.__version__, 'cv2', cv2.__version__)"; } 2>&1

( $PY -m pvm_labeler.cli run --dataset folder --root "$PACK" --out "$W/labels" --jobs "$JOBS" --compression lzf \
    --quiet > "$W/labels.log" 2>&1 && touch "$W/labels.ok" ) &
labeller=$!
timeout "${TEACHER_S:-170}" $PY -m optstereo.cli distill maps --checkpoint pretrained-accurate --root "$PACK" --out "$W/maps" --device "$DEVICE" \
  > "$W/maps.log" 2>&1
rc=$?; [ "$rc" = 0 ] || failed+=(maps); echo "teacher maps: exit $rc at $(elapsed); $(tail -n 1 "$W/maps.log")"
wait "$labeller"
rc=$?; [ "$rc" = 0 ] || failed+=(labels); echo "labels: exit $rc at $(elapsed); $(tail -n 1 "$W/labels.log")"
$PY -m optstereo.cli distill fill "$W/labels" "$W/maps" "$W/distill" --compression lzf --allow-missing > "$W/fill.log" 2>&1
rc=$?; [ "$rc" = 0 ] || failed+=(fill); echo "fill: exit $rc at $(elapsed); $(tail -n 1 "$W/fill.log")"
[ -f "$W/distill/index.json" ] && $PY - "$W/distill/index.json" "$OUTD/distill.json" <<'EOF'
import json, sys
index = json.load(open(sys.argv[1]))
keep = {k: index[k] for k in ("num_samples", "distill", "distilled_from", "dataset") if k in index}
json.dump(keep, open(sys.argv[2], "w"), indent=2)
print(keep.get("num_samples"), "samples in the distilled shards")
EOF

minutes=$($PY -c "print(max(0.2, ($T0 + $TOTAL_S - 45 - $(date +%s)) / 60))")  # 45 s: export, timing, copies
echo "training both for at most $minutes min from $(elapsed)"
common=(--lambda-t 0 --conf-weight --labels "$W/distill" --device "$DEVICE" --amp "$AMP"
        --batch-size "$BATCH" --crop "$CROP" --workers "$WORKERS" --threads "$THREADS" --ckpt-every 500
        --schedule onecycle --max-minutes "$minutes" --quiet)
$PY -m optstereo.cli train --config pipelines/studies/recipes/cpu_main.yaml --init pretrained-accurate --out "$W/student" \
  --steps "$STUDENT_STEPS" --lr 1e-4 --seed 40 --iters "$ITERS" --scale-range 1.0,1.0 "${common[@]}" \
  --set inference.scale=1.0 --set inference.refine=none --set inference.coarse_start=false --set inference.select=false \
  --set inference.select_jump=0 --set inference.adaptive_ref_disp=0 --set inference.adaptive_ref_pixels=0 \
  > "$W/student.log" 2>&1 &
student=$!
$PY -m optstereo.cli train --model hitnet --out "$W/fast" --steps "$FAST_STEPS" --lr 4e-4 --seed 41 --photometric \
  "${common[@]}" > "$W/fast.log" 2>&1 &
fast=$!
wait "$student"; rc=$?; [ "$rc" = 0 ] || failed+=(student)
echo "student: exit $rc at $(elapsed); $(tail -n 2 "$W/student.log" | tr '\n' ' ')"
wait "$fast"; rc=$?; [ "$rc" = 0 ] || failed+=(fast)
echo "fast: exit $rc at $(elapsed); $(tail -n 2 "$W/fast.log" | tr '\n' ' ')"
for name in student fast; do
  cp "$W/$name/model.safetensors" "$OUTD/$name.safetensors" 2>/dev/null || echo "no $name export"
  cp "$W/$name/metrics.jsonl" "$OUTD/${name}_metrics.jsonl" 2>/dev/null
done
tail -n 3 "$W/student/metrics.jsonl" "$W/fast/metrics.jsonl" 2>/dev/null
if [ "$DEVICE" = cuda ]; then
  timeout 40 $PY -m pipelines.studies.gpu.cuda_timing --out "$OUTD/cuda_times.json" --repeats 10 --warmup 3 \
    --end-to-end student="$W/student/model.safetensors" fast="$W/fast/model.safetensors" > "$W/timing.log" 2>&1
  rc=$?; [ "$rc" = 0 ] || failed+=(timing); echo "cuda timing: exit $rc at $(elapsed)"
  cat "$OUTD/cuda_times.json" 2>/dev/null
fi
echo "session end at $(elapsed)${failed[*]:+; FAILED: ${failed[*]}}"
[ "${#failed[@]}" = 0 ]  # the exit status: non-zero when a stage failed (its log above says why)

#!/usr/bin/env bash
# Issue 49 on a lent GPU in TWO back-to-back device calls (a warm machine keeps /tmp/pv for 30 s between calls):
#   call 1: run(command="PART=A GRAPH=1 bash pipelines/studies/gpu/teacher_all.sh", carry=[".carry/A"], timeout_s=330)
#   call 2: run(command="PART=B TRAIN=1 bash pipelines/studies/gpu/teacher_all.sh", carry=[".carry/B"], timeout_s=480)
# Or ONE call, a whole chapter on one pack (G3; the next, G4, as registered in docs/registrations.md):
#   run(command="NAME=G4 PART=D TRAIN=1 SCHEDULE=constant LR=2e-5 SNAPS=3 SPLIT=2 MISSING=drop FILLS=0 SEED=51
#       JOBS=10 END_S=540 TEACHER_S=300 bash pipelines/studies/gpu/teacher_all.sh", carry=[".carry/D"], timeout_s=590)
#   (pack D: python -m pipelines.studies.gpu.pack_c .carry/D --quality 88 --exclude pipelines/studies/valset_indoor.txt)
#   (pack D from scratch, one command: bash pipelines/studies/gpu/build_pack_d.sh /work/.mirror: ../shared/data and
#   three fetched snapshots, its header says which; 212 pairs, 34.0 MB, checked against pack_d_manifest.txt)
#   then, here: python -m pipelines.studies.judge_chapter FILES_AT/G4-*.safetensors --valset VAL --out DIR --gt
# Packs, here, once (WebP, the highest quality under 37 MB each; pipelines/studies/gpu/distill_pack.py):
#   A = the 144 unlabelled pairs of ../shared/data; B = the 267 more that fetch_unlabelled_more.sh copies (less the 57
#   that are byte-identical to A's).
# Each call:
#   1. (GRAPH=1) the gpu-marked tests and the CUDA timings of the shipped default (eager and CUDA-graphed), GPU alone;
#   2. PVM labels of .carry/$PART (all cores, lzf shards) in the background, while the teacher (`pretrained-accurate`,
#      version 14 as shipped, float32) writes both views of every pair (optstereo-distill maps);
#   3. optstereo-distill fill -> $W/distill_$PART (PVM labels + the teacher's LR-consistent views in PVM's holes at
#      weight 0.5); the fills as KITTI 16-bit PNGs -> $OUT/fills_$PART.tar.part* (so the CPU can rebuild the shards);
#   4. (TRAIN=1) every $W/distill_* merged; candidate G1 trained until END_S after the call's start: the default
#      (`pretrained`, version 15) + the student recipe of version 15 (L_P confidence-weighted + 0.1 L_R + 0.1 L_S, no
#      L_T, bf16, batch 8, 320x960, N_s 8, flip-swap, OneCycle peak LR), snapshots at half and at the end.
# $OUT: session_$PART.log, fills_$PART.tar.part0N (cat them), cuda_timing.json, gpu_tests.txt; G1-<step>.safetensors, g1_metrics.jsonl.
# Knobs of later chapters (defaults = G1's): NAME (snapshot prefix, G1), SCHEDULE (onecycle | constant), SNAPS (snapshots
# evenly over the run, 2), SPLIT (teacher processes side by side on the GPU, 1), FILLS (1: send the fills back, 0: skip
# them), GPUTESTS (1: the gpu-marked tests in the background while the data is made, $OUT/gpu_tests.txt), MISSING
# (keep: a pair the teacher's box missed trains on PVM's labels alone, as G1 and G3 did; drop: only the shards all of
# whose pairs have maps train).
# CPU smoke run (tests/studies/test_gpu_script.py runs G4's call this way): DEVICE=cpu AMP=none BATCH=1 CROP=64x128 ITERS=1 PROBE=2 END_S=100000 STEPS_MAX=4 WORKERS=0 \
#   THREADS=2 JOBS=2 TEACHER=<small checkpoint> INIT=<small checkpoint> PACK=<small pack> PART=A TRAIN=1 bash ...
set -uo pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
T0=$(date +%s)
PART=${PART:?PART=A or B}
PACK=${PACK:-.carry/$PART}
GRAPH=${GRAPH:-0} TRAIN=${TRAIN:-0}
END_S=${END_S:-450}            # training ends by T0 + END_S (the call's limit must be larger)
DEVICE=${DEVICE:-cuda} AMP=${AMP:-bf16} BATCH=${BATCH:-8} CROP=${CROP:-320x960} ITERS=${ITERS:-8}
LR=${LR:-5e-5} SEED=${SEED:-49} PROBE=${PROBE:-20} STEPS_MAX=${STEPS_MAX:-100000}
TEACHER=${TEACHER:-pretrained-accurate} INIT=${INIT:-pretrained}
WORKERS=${WORKERS:-6} THREADS=${THREADS:-4} JOBS=${JOBS:-$(nproc)}
NAME=${NAME:-G1} SCHEDULE=${SCHEDULE:-onecycle} SNAPS=${SNAPS:-2} SPLIT=${SPLIT:-1} FILLS=${FILLS:-1}
GPUTESTS=${GPUTESTS:-0} MISSING=${MISSING:-keep}
W=${WORK:-/tmp/pv}
OUTD=${OUT:-/tmp/out}
PY=${PY:-python3}
mkdir -p "$OUTD" "$W"
exec > >(tee -a "$OUTD/session_$PART.log") 2>&1
elapsed() { echo "+$(( $(date +%s) - T0 )) s"; }
failed=()  # the stages that failed: the call exits non-zero when any did
gpu_tests() {  # limit in s -> $OUT/gpu_tests.txt and one line here
  timeout "$1" $PY -m pytest -q -p no:cacheprovider -m gpu tests/test_gpu.py tests/test_graphed.py > "$OUTD/gpu_tests.txt" 2>&1
  echo "gpu tests: exit $? at $(elapsed) ($(tail -n 1 "$OUTD/gpu_tests.txt"))"
}
echo "teacher_all $PART start $(date -u +%FT%TZ); earlier parts here: $(ls -d "$W"/distill_* 2>/dev/null | tr '\n' ' ')"
{ git rev-parse --short HEAD 2>/dev/null; nproc; command -v nvidia-smi > /dev/null && nvidia-smi -L
  $PY -c "import torch, cv2; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'cv2', cv2.__version__)"
} 2>&1

if [ "$GRAPH" = 1 ]; then
  gpu_tests 100
  timeout 90 $PY -m pipelines.studies.gpu.cuda_timing --graphs-only --out "$OUTD/cuda_timing.json" --repeats 10 --warmup 3 \
    > "$W/timing.log" 2>&1
  echo "cuda timing: exit $? at $(elapsed)"; tail -n 30 "$W/timing.log"
fi

if [ "$GPUTESTS" = 1 ]; then
  gpu_tests 150 &  # beside the data stage
fi
( nice -n 5 $PY -m pvm_labeler.cli run --dataset folder --root "$PACK" --out "$W/labels_$PART" --jobs "$JOBS" \
    --compression lzf --quiet > "$W/labels_$PART.log" 2>&1 && touch "$W/labels_$PART.ok" ) &
labeller=$!
# SPLIT teacher processes, each over its share of the pairs (link packs; one maps folder)
teachers=()
for ((i = 0; i < SPLIT; i++)); do
  sub="$W/teacher_pack_$PART$i"; rm -rf "$sub"; mkdir -p "$sub/left" "$sub/right"
  ls "$PACK/left" | awk -v n="$SPLIT" -v i="$i" 'NR % n == i' | while read -r f; do
    ln -s "$(realpath "$PACK/left/$f")" "$sub/left/$f"; ln -s "$(realpath "$PACK/right/$f")" "$sub/right/$f"; done
  timeout "${TEACHER_S:-170}" $PY -m optstereo.cli distill maps --checkpoint "$TEACHER" --root "$sub" --out "$W/maps" \
    --device "$DEVICE" > "$W/maps_$PART$i.log" 2>&1 &
  teachers+=($!)
done
for t in "${teachers[@]}"; do wait "$t"; echo "teacher maps (pid $t): exit $? at $(elapsed)"; done
echo "teacher maps: $(ls "$W/maps" | grep -c "\.npz$") pairs in $W/maps"
wait "$labeller"; rc=$?; [ "$rc" = 0 ] || failed+=(labels)
echo "labels: exit $rc at $(elapsed); $(tail -n 1 "$W/labels_$PART.log")"
if [ "$rc" = 0 ]; then  # the later stages need the labels: after a failure they are skipped, never run on nothing
  $PY -m optstereo.cli distill fill "$W/labels_$PART" "$W/maps" "$W/distill_$PART" --compression lzf --allow-missing \
    > "$W/fill_$PART.log" 2>&1
  rc=$?; [ "$rc" = 0 ] || failed+=(fill)
  echo "fill: exit $rc at $(elapsed); $(tail -n 1 "$W/fill_$PART.log")"
else
  echo "fill, fills and training: skipped (the labels failed; $W/labels_$PART.log says why)"
fi
data_ok=0; [ "${#failed[@]}" = 0 ] && data_ok=1
[ "$data_ok" = 1 ] || { FILLS=0; TRAIN=0; }
[ "$FILLS" = 1 ] && ( $PY -m pipelines.studies.gpu.teacher_all fills "$W/labels_$PART" "$W/maps" "$W/fills_$PART" \
    && tar -cf "$W/fills_$PART.tar" -C "$W" "fills_$PART" && echo "fills tar $(du -m "$W/fills_$PART.tar" | cut -f1) MB" ) \
  > "$W/fills_$PART.log" 2>&1 &
filler=$!

if [ "$TRAIN" = 1 ]; then
  keep=(); [ "$MISSING" = drop ] && keep=(--maps "$W/maps")
  $PY -m pipelines.studies.gpu.teacher_all merge "$W/distill_all" "$W"/distill_? "${keep[@]}" \
    || { failed+=(merge); TRAIN=0; echo "merge: failed at $(elapsed): $NAME not trained"; }
fi
if [ "$TRAIN" = 1 ]; then
  train() {  # out dir, steps, extra args
    $PY -m optstereo.cli train --config pipelines/studies/recipes/cpu_main.yaml --init "$INIT" --lambda-t 0 \
      --conf-weight --labels "$W/distill_all" --out "$1" --steps "$2" --lr "$LR" --seed "$SEED" --device "$DEVICE" \
      --amp "$AMP" --batch-size "$BATCH" --crop "$CROP" --iters "$ITERS" --workers "$WORKERS" --threads "$THREADS" \
      --scale-range 1.0,1.0 --schedule "$SCHEDULE" --quiet "${@:3}"
  }
  rm -rf "$W/probe"; step_s=
  train "$W/probe" "$PROBE" --log-every 2 --ckpt-every 100000 --schedule constant
  step_s=$($PY -c "
import json, sys
rows = [json.loads(line) for line in open('$W/probe/metrics.jsonl')]
half = rows[len(rows) // 2:]
print(sum(r['step_time_s'] for r in half) / len(half))" 2>/dev/null)
fi
if [ "$TRAIN" = 1 ] && [ -z "$step_s" ]; then  # no made-up step time: the probe's failure is the call's
  failed+=(probe); echo "probe: failed (no step times in $W/probe/metrics.jsonl): $NAME not trained"
elif [ "$TRAIN" = 1 ]; then
  budget=$(( T0 + END_S - $(date +%s) - 30 ))  # 30 s: start-up, snapshots, copies
  steps=$($PY -c "print(min($STEPS_MAX, max(3, int(0.9 * $budget / $step_s) // 2 * 2)))")
  echo "probe: $step_s s/step; $budget s left -> $NAME: $steps steps at $(elapsed)"
  rm -rf "$W/g1"
  train "$W/g1" "$steps" --ckpt-every $(( steps / SNAPS )) --set keep_ckpts="$SNAPS" \
    --max-minutes "$($PY -c "print(max($budget, 6) / 60)")"
  rc=$?; [ "$rc" = 0 ] || failed+=("$NAME")
  echo "$NAME: exit $rc at $(elapsed); $(tail -n 1 "$W/g1/metrics.jsonl" 2>/dev/null | cut -c1-300)"
  $PY -m pipelines.studies.gpu.teacher_all snapshots "$W/g1" "$OUTD" --name "$NAME"
  cp "$W/g1/metrics.jsonl" "$OUTD/${NAME,,}_metrics.jsonl" 2>/dev/null
fi
if [ "$FILLS" = 1 ]; then
  wait "$filler"; echo "fills: exit $? at $(elapsed); $(tail -n 2 "$W/fills_$PART.log" | tr '\n' ' ')"
fi
# $OUT brings back at most 8 files of <= 16 MiB, 64 MiB in all: the fills go in 15 MiB parts while they fit
room=$(( 62 * 1024 * 1024 - $(du -cb "$OUTD" | tail -n 1 | cut -f1) ))
if [ "$FILLS" != 1 ]; then
  echo "fills not sent back (FILLS=$FILLS)"
elif [ -f "$W/fills_$PART.tar" ] && [ "$(stat -c %s "$W/fills_$PART.tar")" -le "$room" ]; then
  split -b 15m -d "$W/fills_$PART.tar" "$OUTD/fills_$PART.tar.part"
else
  echo "fills_$PART.tar ($(stat -c %s "$W/fills_$PART.tar" 2>/dev/null) bytes) does not fit the $room bytes left in \$OUT: not sent back"
fi
ls -l "$OUTD"
echo "teacher_all $PART end at $(elapsed)${failed[*]:+; FAILED: ${failed[*]}}"
[ "${#failed[@]}" = 0 ]  # the exit status: non-zero when a stage failed (its log above says why)

#!/usr/bin/env bash
# Everything a lent GPU is wanted for, in ONE device call of at most ~9.5 minutes (a task gets 15 minutes of device
# time, the machine's start included, and no second start fits after a full call):
#   1. PVM labels of the carried pack on 12 cores (lzf shards), in the background, while
#   2. the gpu-marked tests run (tests/test_gpu.py: CUDA vs CPU, fp16 + GradScaler, bf16, L_T, predict; the
#      wmedian filter on CUDA vs the CPU kernel, tests/test_refine_torch.py);
#   3. KITTI-size inference time on CUDA, alone on the machine (pipelines/studies/gpu/cuda_timing.py);
#   4. continue.sh: the lineage's continuation at GPU size, sized to end by T0 + TOTAL_S.
# Device: run(command="bash pipelines/studies/gpu/session.sh", carry=[".carry/unl"], timeout_s=600)
# $OUT receives session.log, gpu_tests.txt, cuda_timing.json and continue.sh's files (NAME.safetensors, ...).
set -uo pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
T0=$(date +%s)
TOTAL_S=${TOTAL_S:-540}
OUTD=${OUT:-/tmp/out}
W=${WORK:-/tmp/pv}
PY=${PY:-python3}
mkdir -p "$OUTD" "$W"
exec > >(tee -a "$OUTD/session.log") 2>&1
echo "session start $(date -u +%FT%TZ), training ends by +$TOTAL_S s"
failed=()  # the stages that failed: the call exits non-zero when any did

( $PY -m pvm_labeler.cli run --dataset folder --root "${PACK:-.carry/unl}" --out "$W/labels" \
    --jobs "${LABEL_JOBS:-12}" --compression lzf --quiet > "$W/labels.log" 2>&1 && touch "$W/labels.ok" ) &
labeller=$!

timeout 200 $PY -m pytest -q -p no:cacheprovider -m gpu tests/test_gpu.py tests/test_refine_torch.py > "$OUTD/gpu_tests.txt" 2>&1
rc=$?; [ "$rc" = 0 ] || failed+=(tests); echo "gpu tests: exit $rc ($(tail -n 1 "$OUTD/gpu_tests.txt"))"
wait "$labeller"
rc=$?; [ "$rc" = 0 ] || failed+=(labels)
echo "labels: exit $rc at +$(( $(date +%s) - T0 )) s; $(tail -n 1 "$W/labels.log")"

timeout 120 $PY -m pipelines.studies.gpu.cuda_timing --out "$OUTD/cuda_timing.json" > "$W/timing.log" 2>&1
rc=$?; [ "$rc" = 0 ] || failed+=(timing)
echo "cuda timing: exit $rc at +$(( $(date +%s) - T0 )) s; $(tail -n 1 "$W/timing.log")"
[ -f "$OUTD/cuda_timing.json" ] && cat "$OUTD/cuda_timing.json"

END_AT=$((T0 + TOTAL_S)) WORK="$W" OUT="$OUTD" bash "$(dirname "$0")/continue.sh" || failed+=(continue)
echo "session end at +$(( $(date +%s) - T0 )) s${failed[*]:+; FAILED: ${failed[*]}}"
[ "${#failed[@]}" = 0 ]  # the exit status: non-zero when a stage failed (its log above says why)

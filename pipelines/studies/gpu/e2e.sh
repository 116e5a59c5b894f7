#!/usr/bin/env bash
# E7 / G5 (docs/registrations.md) on a lent GPU in ONE device call: four students trained side by side on one GPU,
# end to end, each to reproduce a teacher network run on its very crops (pipelines/studies/e2e_distill.py):
#   E7a  E4's file at scale 1 (E5, both first encoder stages separable) <- version 15, lr 5e-5
#   E7b  the same                                                      <- version 15, lr 1.5e-5
#   G5a  version 15                                                    <- version 14 (`pretrained-accurate`'s
#        network) at input scale 1.625 with its coarse start, one pass, no choice and no filter, lr 2e-5
#   G5b  the same, lr 5e-5
# and the gpu-marked tests in the background.
# Here, once:
#   python -m pipelines.studies.gpu.distill_pack .carry/A --part shared --format webp --budget-mb 37
#   git show 73a900faf3f861b1c9fba98e4f4adb2bae2513ad:results/cheap_layer1/e4/e4_stages.safetensors > /tmp/e4.st
#   mkdir -p .carry/E && cp /tmp/e4.st .carry/E/e4_stages.safetensors   (E4's students alone: the call exports E5)
# Device:
#   run(command="bash pipelines/studies/gpu/e2e.sh", carry=[".carry/A", ".carry/E"], timeout_s=560)
# $OUT (8 files, 64 MiB at most): e2e.log, logs.tar (each run's .jsonl and output, the gpu tests), snapshots
#   <name>-<step>.safetensors: E7a and G5a at half and at the end, E7b and G5b at the end.
# CPU smoke run: DEVICE=cpu AMP=none BATCH=1 CROP=64x128 END_S=20 THREADS=1 OUT=/tmp/e2e bash pipelines/studies/gpu/e2e.sh
set -uo pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
END_S=${END_S:-450}
DEVICE=${DEVICE:-cuda} AMP=${AMP:-bf16} BATCH=${BATCH:-8} CROP=${CROP:-320x960} THREADS=${THREADS:-4}
OUTD=${OUT:-/tmp/out}
PY=${PY:-python3}
mkdir -p "$OUTD/logs"
exec > >(tee -a "$OUTD/e2e.log") 2>&1
echo "e2e start $(date -u +%FT%TZ), each run trains $END_S s"
{ git rev-parse --short HEAD 2>/dev/null; nproc; command -v nvidia-smi > /dev/null && nvidia-smi -L
  $PY -c "import torch, cv2; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'cv2', cv2.__version__)"
} 2>&1
common=(--pack .carry/A --out "$OUTD" --device "$DEVICE" --amp "$AMP" --batch "$BATCH" --crop "$CROP"
        --end-s "$END_S" --threads "$THREADS")
run() {  # name, then the run's own arguments; its exit status is the run's
  local name=$1 rc; shift
  $PY -m pipelines.studies.e2e_distill train --name "$name" "${common[@]}" "$@" > "$OUTD/logs/$name.out" 2>&1
  rc=$?; echo "$name: exit $rc at $(date -u +%T)"; return "$rc"
}
$PY -m pipelines.studies.cheap_layer1 export --state .carry/E/e4_stages.safetensors --out /tmp/e5.safetensors || exit 1
pids=()
if [ "$DEVICE" = cuda ]; then
  timeout 200 $PY -m pytest -q -p no:cacheprovider -m gpu tests/test_gpu.py tests/test_graphed.py \
    > "$OUTD/logs/gpu_tests.txt" 2>&1 & pids+=($!)
fi
e5=/tmp/e5.safetensors v14=(--teacher pretrained-accurate --teacher-scale 1.625 --teacher-coarse)
run E7a --student $e5 --teacher pretrained --lr 5e-5 --seed 70 --snaps 2 & pids+=($!)
run E7b --student $e5 --teacher pretrained --lr 1.5e-5 --seed 71 --snaps 1 & pids+=($!)
run G5a --student pretrained "${v14[@]}" --lr 2e-5 --seed 72 --snaps 2 & pids+=($!)
run G5b --student pretrained "${v14[@]}" --lr 5e-5 --seed 73 --snaps 1 & pids+=($!)
failed=0  # how many runs failed: the call exits non-zero when any did
for pid in "${pids[@]}"; do  # not a bare wait: it would wait for the tee above, which ends only with this script
  wait "$pid" || failed=$((failed + 1))
done
[ -e "$OUTD/logs/gpu_tests.txt" ] && echo "gpu tests: $(tail -n 1 "$OUTD/logs/gpu_tests.txt")"
mv "$OUTD"/*.jsonl "$OUTD/logs/" 2>/dev/null
tar -cf "$OUTD/logs.tar" -C "$OUTD" logs && rm -r "$OUTD/logs"
for f in "$OUTD"/*.jsonl "$OUTD"/logs.tar; do [ -e "$f" ] && echo "kept $f"; done
ls -la "$OUTD"
echo "e2e end $(date -u +%FT%TZ); $failed failed"
[ "$failed" = 0 ]

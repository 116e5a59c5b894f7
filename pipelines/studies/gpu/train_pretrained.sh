#!/usr/bin/env bash
# The shipped model's recipe at paper size for a lent H100, written but NOT run yet (the one session lent a GPU had 15
# minutes of device time, which session.sh used; its calls need more, RESULTS.md). Run with the device tool from the
# repo root; .carry/unl carried:
# `python -m pipelines.studies.carry_pack --dataset kitti_unlabelled --root ../shared/data/kitti_unlabelled .carry/unl`.
#   bash pipelines/studies/gpu/train_pretrained.sh start    env, PVM labels (JPEG pack, 16 cores), gpu tests, probe, launch
#   bash pipelines/studies/gpu/train_pretrained.sh poll S   watch the runs for S seconds, then snapshot weights into $OUT
#   bash pipelines/studies/gpu/train_pretrained.sh finish   wait for the main run, snapshot
# Runs live in /root/pv on the machine (kept while it stays warm); every snapshot lands in $OUT.
set -uo pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD OMP_NUM_THREADS=2
W=/root/pv
OUTD=${OUT:-/tmp/out}
PY=python3
MAIN_BUDGET_S=${MAIN_BUDGET_S:-1200}   # wall seconds the main run may use (ends before the device lease does)
ABL_BUDGET_S=${ABL_BUDGET_S:-420}
mkdir -p "$W" "$OUTD"

train() {  # name, recipe, extra args...: launched in its own session so it outlives this device call
  local name=$1 recipe=$2; shift 2
  echo "$PY -m optstereo.cli train --config pipelines/studies/recipes/$recipe --labels $W/labels --out $W/runs/$name $*" \
    | tee -a "$W/commands.txt"
  setsid nohup $PY -m optstereo.cli train --config "pipelines/studies/recipes/$recipe" --labels "$W/labels" \
    --out "$W/runs/$name" --quiet "$@" > "$W/runs/$name.log" 2>&1 < /dev/null &
}

probe() {  # name, recipe, extra args...: seconds per step (mean of steps 11-30)
  local name=$1 recipe=$2; shift 2
  $PY -m optstereo.cli train --config "pipelines/studies/recipes/$recipe" --labels "$W/labels" --out "$W/probe/$name" \
    --steps 30 --log-every 10 --ckpt-every 1000 --quiet "$@" > "$W/probe/$name.log" 2>&1
  $PY - "$W/probe/$name/metrics.jsonl" <<'PYEOF'
import json, sys
rows = [json.loads(line) for line in open(sys.argv[1])]
print(sum(r["step_time_s"] for r in rows[1:]) / len(rows[1:]))
PYEOF
}

snapshot() {
  $PY - "$W" "$OUTD" <<'PYEOF'
import sys, tarfile
from pathlib import Path
from optstereo.checkpoint import load_checkpoint, build_model_from_checkpoint, export_safetensors
w, out = Path(sys.argv[1]), Path(sys.argv[2])
for run in sorted((w / "runs").glob("*/")):
    if (run / "last.pt").exists():
        ckpt = load_checkpoint(run / "last.pt")
        model = build_model_from_checkpoint(ckpt)
        export_safetensors(out / f"{run.name}.safetensors", model, step=ckpt.step)
        print(f"snapshot {run.name} at step {ckpt.step}")
with tarfile.open(out / "logs.tar.gz", "w:gz") as tar:
    for path in [w / "commands.txt", w / "env.txt", *w.glob("probe/*.log"), *w.glob("runs/*.log")]:
        if path.exists():
            tar.add(path, arcname=str(path.relative_to(w)))
    for run in (w / "runs").glob("*/"):
        for name in ("metrics.jsonl", "config.yaml", "summary.json"):
            if (run / name).exists():
                tar.add(run / name, arcname=f"runs/{run.name}/{name}")
PYEOF
}

watch() {  # seconds
  local end=$((SECONDS + $1))
  while [ $SECONDS -lt $end ]; do
    sleep 60
    for f in "$W"/runs/*/metrics.jsonl; do
      [ -f "$f" ] && echo "$(basename "$(dirname "$f")"): $(tail -n 1 "$f" | cut -c1-230)"
    done
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
  done
}

case ${1:-} in
  start)
    { date -u; nvidia-smi -L; nproc; $PY -c "import torch, numba, h5py, cv2, numpy; print('torch', torch.__version__,
      'numba', numba.__version__, 'h5py', h5py.__version__, 'cv2', cv2.__version__, 'numpy', numpy.__version__)"; } \
      | tee "$W/env.txt"
    t0=$SECONDS
    $PY -m pvm_labeler.cli run --dataset folder --root .carry/unl --out "$W/labels" --jobs 8 --compression lzf \
      --quiet 2>&1 | tail -n 3
    echo "labels in $((SECONDS - t0)) s"
    $PY -m pytest -q -p no:cacheprovider -m gpu tests/test_gpu.py 2>&1 | tail -n 15
    mkdir -p "$W/probe" "$W/runs"
    t_main=$(probe main pretrained.yaml)
    t_abl=$(probe abl ablation.yaml --lambda-t 0.5)
    echo "probe s/step: main $t_main, ablation with L_T $t_abl" | tee -a "$W/env.txt"
    # Four runs share the GPU for the ablations' duration: allow 1.3x (main) and 1.6x (ablations) slower steps.
    s_main=$($PY -c "print(int($MAIN_BUDGET_S / ($t_main * 1.3)) // 50 * 50)")
    s_abl=$($PY -c "print(int($ABL_BUDGET_S / ($t_abl * 1.6)) // 50 * 50)")
    echo "steps: main $s_main, ablation $s_abl" | tee -a "$W/env.txt"
    train main pretrained.yaml --steps "$s_main" --analogy-start $((s_main / 5)) \
      --max-minutes "$($PY -c "print($MAIN_BUDGET_S / 60 + 1)")"
    train abl_full_t ablation.yaml --steps "$s_abl" --lambda-t 0.5 --analogy-start $((s_abl / 5))
    train abl_full ablation.yaml --steps "$s_abl" --lambda-t 0
    train abl_lp ablation.yaml --steps "$s_abl" --lambda-t 0 --lambda-r 0 --lambda-s 0
    watch $(( ${2:-540} - SECONDS ))
    snapshot
    ;;
  poll)
    watch "${2:-540}"
    snapshot
    ;;
  finish)
    while pgrep -f "runs/main " > /dev/null && [ $SECONDS -lt "${2:-540}" ]; do sleep 15; done
    tail -n 3 "$W/runs/main.log"
    snapshot
    ;;
  *) echo "usage: $0 start|poll SECONDS|finish" >&2; exit 2 ;;
esac

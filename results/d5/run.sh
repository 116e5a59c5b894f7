#!/usr/bin/env bash
# D5 (docs/registrations.md): D4 with N_s = 3 in training (the shipped default's test-time count), 3,000 steps.
set -euo pipefail
cd /work/main
PY=.venv/bin/python
test -f /work/t14/d3/teacher/index.json  # D3's shards (results/d3/run.sh, first half)
nice $PY -m optstereo.cli train --config /work/t12/teacher_only/run/config.yaml \
    --labels /work/t14/d3/teacher --out /work/t15/d5/run --steps 3000 --schedule onecycle --lr 5e-5 --iters 3 \
    --ckpt-every 500 --set keep_ckpts=1000 --max-minutes 70 --threads 2 --seed 0 --init pretrained --quiet

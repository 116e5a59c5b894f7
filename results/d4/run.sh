#!/usr/bin/env bash
# D4 (docs/registrations.md): D3's teacher-only shards of the 144 unlabelled pairs (made by results/d3/run.sh),
# D3's settings but a decaying rate: OneCycle (linear), peak 5e-5, 2,800 steps, a checkpoint every 400.
set -euo pipefail
cd /work/main
PY=.venv/bin/python
test -f /work/t14/d3/teacher/index.json  # D3's shards (results/d3/run.sh, first half)
nice $PY -m optstereo.cli train --config /work/t12/teacher_only/run/config.yaml \
    --labels /work/t14/d3/teacher --out /work/t15/d4/run --steps 2800 --schedule onecycle --lr 5e-5 \
    --ckpt-every 400 --set keep_ckpts=1000 --max-minutes 80 --threads 2 --seed 0 --init pretrained --quiet

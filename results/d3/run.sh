#!/usr/bin/env bash
# D3 (docs/registrations.md): teacher-only shards of the 144 unlabelled pairs, then 70 minutes of the
# adaptation's teacher-only training settings from pretrained, a checkpoint every 600 steps.
set -euo pipefail
cd /work/main
PY=.venv/bin/python
$PY - <<'PY'
from pathlib import Path
from optstereo.training import distill
distill.fill(Path("/work/w2/labels"), Path("/work/w2/maps"), Path("/work/t14/d3/teacher"), compression="lzf",
             teacher_only=True)
PY
nice $PY -m optstereo.cli train --config /work/t12/teacher_only/run/config.yaml \
    --labels /work/t14/d3/teacher --out /work/t14/d3/run --steps 1000000000 --ckpt-every 600 \
    --set keep_ckpts=1000 --max-minutes 70 --threads 2 --seed 0 --init pretrained --quiet

#!/usr/bin/env bash
# W2 (docs/registrations.md): labels, fills, 50 minutes of G2's recipe from pretrained, every checkpoint kept
set -euo pipefail
cd /work/main
PY=.venv/bin/python
$PY -m pvm_labeler.cli run --dataset folder --root /work/pack/shared --out /work/w2/labels --shard-size 1 \
    --compression lzf --jobs 2 --quiet
$PY -m optstereo.cli distill fill /work/w2/labels /work/w2/maps /work/w2/filled --compression lzf --allow-missing
nice $PY -m optstereo.cli train --config pipelines/studies/recipes/cpu_main.yaml --lambda-t 0 --conf-weight \
    --schedule constant --lr 2e-5 --scale-range 1.0,1.0 --batch-size 2 --crop 256x640 --iters 4 \
    --set inference.iters=8 --set keep_ckpts=1000 --labels /work/w2/filled --steps 1000000000 --ckpt-every 100 \
    --seed 0 --init pretrained --out /work/w2/run --max-minutes 50 --threads 2 --quiet

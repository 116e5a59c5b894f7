#!/usr/bin/env bash
# Issue 42, candidate F3 `fast_half` (RESULTS.md, "Candidates scored"): the default's weights fine-tuned on 2 CPU cores
# to run at input scale 0.5, on PVM labels of 411 unlabelled real pairs plus the default's own consistent dense output
# in PVM's holes. Every step is resumable; rerunning the script continues where it stopped.
#   MIRRORS=/work/.mirror bash pipelines/studies/fast_half.sh      # snapshots fetched with the search tool's `fetch`
# Needs: the six repositories of ../shared/data/fetch_unlabelled_more.sh (sections A-F) under $MIRRORS.
set -euo pipefail
W=${WORK:-/work/f3}
MIRRORS=${MIRRORS:?MIRRORS: the folder holding the fetched snapshots, one <owner>+<name>/ each}
PY=${PY:-.venv/bin/python}
STEPS=${STEPS:-1300}
mkdir -p "$W"
if [ ! -d "$W/fetched" ]; then   # section G (three single captures) needs snapshots we do not fetch: stop before it
  sed '/^# G\./,$d' ../shared/data/fetch_unlabelled_more.sh > "$W/fetch_a_to_f.sh"
  bash "$W/fetch_a_to_f.sh" "$W/fetched.tmp" "$MIRRORS" && mv "$W/fetched.tmp" "$W/fetched"
fi
[ -d "$W/pack" ] || { $PY -m pipelines.studies.fast_pack "$W/pack.tmp" --fetched "$W/fetched" && mv "$W/pack.tmp" "$W/pack"; }
$PY -m pvm_labeler.cli run --dataset folder --root "$W/pack" --out "$W/labels" --jobs 2 --compression lzf
$PY -m optstereo.cli distill maps --checkpoint pretrained --root "$W/pack" --out "$W/maps" --device cpu
[ -f "$W/distill/index.json" ] || $PY -m optstereo.cli distill fill "$W/labels" "$W/maps" "$W/distill" --compression lzf
if [ -f "$W/run/last.pt" ]; then
  nice -n 5 $PY -m optstereo.cli train --resume "$W/run" --quiet
else
  nice -n 5 $PY -m optstereo.cli train --config pipelines/studies/recipes/cpu_main.yaml --init pretrained \
    --labels "$W/distill" --out "$W/run" --steps "$STEPS" --lr 1e-4 --seed 43 --iters 8 --scale-range 0.5,0.5 \
    --lambda-t 0 --conf-weight --batch-size 4 --crop 176x448 --schedule onecycle --amp bf16 --threads 2 --workers 1 \
    --ckpt-every 100 --max-minutes 85 --quiet \
    --set inference.refine=none --set inference.adaptive_ref_disp=60.1 --set inference.adaptive_ref_pixels=465750
fi

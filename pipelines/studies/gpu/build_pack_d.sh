#!/usr/bin/env bash
# Pack D (G4's and G6's image pack, carried to a lent GPU as .carry/D) rebuilt in one command from nothing but
# ../shared/data and three git snapshots fetched with the `fetch` tool:
#   bash pipelines/studies/gpu/build_pack_d.sh MIRRORS [WORK]
#     MIRRORS: the folder holding the snapshots as <owner>+<name>/repo (a bare git dir or a clone), e.g. /work/.mirror
#     WORK:    scratch folder (default /work/pack_build); only its sub-folders named below are replaced
#   env: OUT (default .carry/D), SHARED (default ../shared/data), PY (default .venv/bin/python, else python3)
# Run from anywhere; it works in the repository root. The chain, every step into WORK:
#   1. the 57 table-top pairs (l-lattermann/Stereo-Dataset, section C of ../shared/data/fetch_unlabelled_more.sh,
#      same commit and names) -> WORK/unl_more/indoor_rccube_lattermann. The other sections of that script (KITTI
#      clips, misc pairs: 7 more mirrors) feed packs B and `more`, not pack D, so they are not fetched here;
#   2. pipelines/studies/fetch_unlabelled_extra.sh WORK/unl_extra MIRRORS (50 InStereo2K rooms, 24 ZED frames);
#   3. distill_pack.py: pack A (the 144 pairs of ../shared, WebP, highest quality under 37 MB: q90) -> WORK/A; the
#      extra link pack -> WORK/extra; the table-tops at half size -> WORK/tabletop_half;
#   4. pack_c.py OUT --quality 88 --exclude pipelines/studies/valset_indoor.txt with --links WORK/extra
#      WORK/tabletop_half --pack-a WORK/A, then its pair names compared with pipelines/studies/gpu/pack_d_manifest.txt
#      (exit 1 naming the missing and extra pairs when they differ).
# Prints the pack's pairs and MB (212 pairs, 34.0 MB at q88; with the ~30 MB tracked tree ~61 MiB of the device's
# 64 MiB carry, 2026-11-29; ~2 min). Nothing under /work/pack or .carry/A is touched.
set -euo pipefail
MIRRORS=${1:?usage: build_pack_d.sh MIRRORS [WORK] (MIRRORS: the folder of fetched snapshots, e.g. /work/.mirror)}
WORK=${2:-/work/pack_build}
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)
MIRRORS=$(realpath -m "$MIRRORS"); WORK=$(realpath -m "$WORK")
cd "$ROOT"
OUT=${OUT:-.carry/D}
SHARED=${SHARED:-../shared/data}
if [ -z "${PY:-}" ]; then if [ -x .venv/bin/python ]; then PY=.venv/bin/python; else PY=python3; fi; fi
MANIFEST=pipelines/studies/gpu/pack_d_manifest.txt
T0=$(date +%s)
step() { echo "[build_pack_d +$(( $(date +%s) - T0 )) s] $*"; }

# The snapshots pack D needs (owner+name commit), the commits those scripts pin.
TABLETOP=29f66e7a75f10bac563284ed150e2810f2e63b2e
NEED=("l-lattermann+Stereo-Dataset $TABLETOP"
      "yzhangtj+StereoVision d919b1045e2833a2dfa2ca8fdd672c3633d8117a"
      "FabianAC07+ZED-and-ZED-Mini-Depth-Estimation-Evaluation 56e890e3c65e4a72c42620a4fab2cf72fc012b4a")
gitdir() { # owner+name -> the snapshot's git dir (a clone's .git or the bare dir), empty when there is none
  local d=$MIRRORS/$1/repo
  [ -d "$d/.git" ] && d=$d/.git
  [ -d "$d/objects" ] && echo "$d"
  return 0; }
problems=()
for entry in "${NEED[@]}"; do
  name=${entry% *}; commit=${entry#* }; d=$(gitdir "$name")
  if [ -z "$d" ]; then
    problems+=("missing mirror $MIRRORS/$name/repo: run fetch github:${name/+//}")
  elif ! git --git-dir "$d" cat-file -e "$commit^{commit}" 2>/dev/null; then
    problems+=("mirror $d lacks commit $commit: run fetch github:${name/+//} again (a newer snapshot)")
  fi
done
[ -d "$SHARED/kitti_unlabelled" ] && [ -d "$SHARED/unlabelled_more" ] \
  || problems+=("no $SHARED/kitti_unlabelled or $SHARED/unlabelled_more (set SHARED)")
if [ ${#problems[@]} -gt 0 ]; then
  printf 'build_pack_d: %s\n' "${problems[@]}" >&2; exit 1
fi

mkdir -p "$WORK"
rm -rf "$WORK/unl_more" "$WORK/unl_extra" "$WORK/A" "$WORK/extra" "$WORK/tabletop_half"

step "1. table-tops from l-lattermann/Stereo-Dataset@${TABLETOP:0:7} -> $WORK/unl_more"
G=$(gitdir l-lattermann+Stereo-Dataset); D=$WORK/unl_more/indoor_rccube_lattermann
mkdir -p "$D/image_2" "$D/image_3"
for n in $(git --git-dir "$G" ls-tree --name-only $TABLETOP dataset/); do n=${n#dataset/}
  git --git-dir "$G" show "$TABLETOP:dataset/$n/${n}_left_img.png" > "$D/image_2/$n.png"
  git --git-dir "$G" show "$TABLETOP:dataset/$n/${n}_right_img.png" > "$D/image_3/$n.png"
done
echo "$(ls "$D/image_2" | wc -l) table-top pairs"

step "2. fetch_unlabelled_extra.sh -> $WORK/unl_extra"
bash pipelines/studies/fetch_unlabelled_extra.sh "$WORK/unl_extra" "$MIRRORS"

step "3. distill_pack: pack A -> $WORK/A, link pack -> $WORK/extra, table-tops at half size -> $WORK/tabletop_half"
export PYTHONPATH=$ROOT${PYTHONPATH:+:$PYTHONPATH} TQDM_DISABLE=1
DP=(nice -n 5 "$PY" -m pipelines.studies.gpu.distill_pack)
"${DP[@]}" "$WORK/A" --part shared --shared "$SHARED" --format webp --budget-mb 37
"${DP[@]}" "$WORK/extra" --part more --shared "$SHARED" --more "$WORK/unl_extra" --format link
"${DP[@]}" "$WORK/tabletop_half" --part more --shared "$SHARED" --more "$WORK/unl_more" \
  --only indoor_rccube_lattermann --halve

step "4. pack_c -> $OUT (WebP q88, less pipelines/studies/valset_indoor.txt), compared with $MANIFEST"
nice -n 5 "$PY" -m pipelines.studies.gpu.pack_c "$OUT" --quality 88 --exclude pipelines/studies/valset_indoor.txt \
  --links "$WORK/extra" "$WORK/tabletop_half" --pack-a "$WORK/A" --manifest "$MANIFEST"
step "done: $(ls "$OUT/left" | wc -l) pairs, $(find "$OUT" -type f -printf '%s\n' | awk '{s += $1} END {printf "%.1f", s / 1e6}') MB in $OUT"

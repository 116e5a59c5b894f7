#!/bin/bash
# Byte-copies MORE real, rectified, UNLABELLED stereo pairs (mostly indoor, plus outdoor non-driving) out of
# fetched git snapshots into the project's `folder` layout, for self-supervised training only:
#   $DEST/<set>/image_2/<id>.png  (left)   and   $DEST/<set>/image_3/<id>.png  (right)
# Read a set with `--dataset folder --root $DEST/<set> --left image_2 --right image_3` (paired by stem).
# Nothing is re-encoded, resized or re-rectified. Only left/right images are copied: NO ground truth (the
# disparity maps these repositories also ship) is taken. None of these images is a KITTI 2012/2015 benchmark
# frame, a Middlebury image, an ETH3D two-view scene, a DrivingStereo frame or Scene Flow, and none of the
# repositories is one used by ../../../shared/data (SOURCES.md, fetch_unlabelled_more.sh) or fetch_valset.sh.
# Every pair was checked: same size, SIFT matches' median |dy| < 1.5 px (0.13-1.47 px), >= 94 % of matches with
# positive disparity (left x > right x), width 320..1600, and 32x32 grey thumbnail correlation <= 0.9 against
# every GT left frame in shared/data, the validation pairs and the existing training pairs (max 0.748).
#
# Usage: fetch_unlabelled_extra.sh DEST MIRRORS
#   MIRRORS holds one git snapshot per repository as <owner>+<name>/repo (a bare git dir or a clone with .git),
#   e.g. /work/.mirror as filled by the `fetch` tool. Commits are pinned; a missing mirror or commit is an error.
#
# Sources (commit pinned; licence = what the repository states; the images keep their datasets' own terms):
#  A. yzhangtj/StereoVision @ d919b1045e2833a2dfa2ca8fdd672c3633d8117a -- no licence file. Its test/<id>/ folders
#     hold the 50 pairs of the InStereo2K TEST split (Bao et al., "InStereo2K: a large real dataset for stereo
#     matching in indoor scenes", Sci. China Inf. Sci. 2020; github.com/YuhuaXu/StereoDataset, no licence stated,
#     research use): 1080x860 RGB PNG, rectified, indoor (rooms, furniture, fabrics, toys). Ids 000040..002006.
#     Its left_disp/right_disp (GT), *_rectified, depth/disparity outputs and the author's own 1762x800
#     pairs test/0100xx/ are NOT copied.                                      -> indoor_instereo2k_test (50)
#  B. FabianAC07/ZED-and-ZED-Mini-Depth-Estimation-Evaluation @ 56e890e3c65e4a72c42620a4fab2cf72fc012b4a --
#     GPL-3.0 (repository licence). Data/<Indoor|Outdoor>/<ZED|ZED-M>/720/{Left,Right}/*-{L1,R1}-NN.png: images
#     rectified by the ZED SDK (the *-UNREC-* files, unrectified, are NOT used), 1280x720 RGB PNG; a target
#     placed at 0.5..3.0 m (NN = 05..30) in front of a ZED (baseline 120 mm) and a ZED Mini (63 mm), so the six
#     frames of one camera/scene are near-duplicates apart from the target. The 1080 (1920-wide) copies are
#     skipped (too wide).           -> indoor_zed_corridor (12: a corridor)  and  outdoor_zed_lawn (12: a lawn)
set -euo pipefail
DEST=${1:?usage: fetch_unlabelled_extra.sh DEST MIRRORS}
M=${2:?MIRRORS: the folder that holds the fetched snapshots, one <owner>+<name>/repo each}
gitdir() { # owner+name commit -> prints the git dir holding that commit, or fails naming what is missing
  local d=$M/$1/repo
  [ -d "$d/.git" ] && d=$d/.git
  [ -d "$d" ] || { echo "missing mirror: $M/$1/repo (fetch github:${1/+//} first)" >&2; exit 1; }
  git --git-dir "$d" cat-file -e "$2^{commit}" 2>/dev/null \
    || { echo "missing commit $2 in mirror $d (fetch a newer snapshot of ${1/+//})" >&2; exit 1; }
  echo "$d"; }
cp1() { # gitdir commit srcpath dstpath
  mkdir -p "$(dirname "$4")"
  git --git-dir "$1" show "$2:$3" > "$4.part" || { echo "cannot read $2:$3 from $1" >&2; rm -f "$4.part"; exit 1; }
  mv "$4.part" "$4"; }

# A. InStereo2K test split (50 indoor pairs)
C=d919b1045e2833a2dfa2ca8fdd672c3633d8117a; G=$(gitdir yzhangtj+StereoVision $C); D=$DEST/indoor_instereo2k_test
for n in 000040 000080 000120 000160 000200 000240 000280 000320 000360 000400 000440 000480 000520 000560 \
         000600 000640 000680 000720 000760 000800 000840 000880 000920 000960 001000 001040 001080 001120 \
         001160 001200 001240 001280 001320 001360 001400 001440 001500 001540 001580 001620 001660 001700 \
         001740 001780 001820 001860 001900 001940 001980 002006; do
  cp1 $G $C test/$n/left.png  $D/image_2/$n.png
  cp1 $G $C test/$n/right.png $D/image_3/$n.png
done

# B. ZED / ZED Mini, SDK-rectified, 720p (12 indoor + 12 outdoor pairs)
C=56e890e3c65e4a72c42620a4fab2cf72fc012b4a; G=$(gitdir FabianAC07+ZED-and-ZED-Mini-Depth-Estimation-Evaluation $C)
for scene in Indoor:INDOOR:indoor_zed_corridor Outdoor:OUTDOOR:outdoor_zed_lawn; do
  dir=${scene%%:*}; rest=${scene#*:}; tag=${rest%%:*}; D=$DEST/${rest#*:}
  for cam in ZED:zed ZED-M:zedm; do
    c=${cam%%:*}; id=${cam#*:}
    for nn in 05 10 15 20 25 30; do
      P=Data/$dir/$c/720
      cp1 $G $C $P/Left/$tag-$c-720-L1-$nn.png  $D/image_2/${id}_$nn.png
      cp1 $G $C $P/Right/$tag-$c-720-R1-$nn.png $D/image_3/${id}_$nn.png
    done
  done
done
echo done

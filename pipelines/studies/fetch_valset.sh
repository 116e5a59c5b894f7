#!/bin/bash
# Byte-copies a GT-free VALIDATION set of 24 real, rectified stereo pairs (12 driving, 12 non-driving) out of
# fetched git snapshots into the project's `folder` layout:
#   $DEST/<group>/image_2/<name>.<ext>  (left)   and   $DEST/<group>/image_3/<name>.<ext>  (right)
# Read a group with `--dataset folder --root $DEST/<group> --left image_2 --right image_3` (paired by stem).
# Nothing is re-encoded or resized: DrivingStereo frames stay JPEG (.jpg in both folders), the rest are PNG.
# Only left/right images are copied: NO ground truth (none of the disparity/depth maps these repositories also
# ship) is taken. None of these images is a KITTI 2012/2015 benchmark frame or a Middlebury image, and none of
# the repositories is one used for training/evaluation data in ../../../shared/data (SOURCES.md,
# fetch_unlabelled_more.sh). Validation only: do not train on these.
#
# Usage: fetch_valset.sh DEST MIRROR_ROOT
#   MIRROR_ROOT holds one git snapshot per repository as <owner>+<name>/repo (a bare git dir or a clone's .git).
#
# Sources (commit pinned; licence = what the repository states; the images keep their datasets' own terms):
#  A. jedld/usam-net-inference @ 36c8f2ec56144e986e00d9172a66bc983bfdcf86 -- MIT (code). Its sample/ and data/
#     folders hold DrivingStereo frames (Yang et al., CVPR 2019; drivingstereo-dataset.github.io; research use),
#     half-size 881x400 / 879x400 JPEG, rectified, car-mounted. 12 pairs from 4 drives:
#     2018-07-09-16-11-56 (4 frames over 3 s, urban boulevard), 2018-07-11-14-48-52 (6 frames over 14 s,
#     ramp under an overpass + traffic), 2018-10-11-16-03-19 (1, side road), 2018-10-19-10-33-08 (1, village lane).
#     The repo's disparity_maps/ and depth_maps/ (GT) are NOT copied.
#  B. ccj5351/ccj5351.github.io @ 34f515936a401a585a307494e9237cf1a3aa6fd5 -- no licence file. Its
#     files/stereo-datasets/ETH3D/two_view_training/{image_0,image_1}/<scene>.png are the ETH3D low-res two-view
#     training pairs (Schoeps et al., CVPR 2017; ETH3D's own terms: CC BY-NC-SA 4.0 per eth3d.net), grey content stored as RGB PNG,
#     707-942 x 425-491, rectified. 10 pairs, one per scene view: outdoor non-driving (loading area, building
#     facades, forest, playground, terrace) and indoor table-top terrain models (terrains_*).
#     Its MiddleburyV3/ and virtual-kitti2/ folders are NOT used.
#  C. srikanthmalla/stereo @ 28fa95963ec870577b280deb05d4db12c5b450de -- no licence stated. left_rectified.png /
#     right_rectified.png: one EuRoC MAV (ETH ASL) Vicon-room frame, 448x320, rectified by the repo author with
#     cv2.stereoRectify (curved black borders). Indoor.
#  D. dhaivat1729/ego_motion_pt_cloud @ dae1383f2ada81c890ee8493c466f77d112dffa7 -- no licence stated.
#     left_rectified.png / right_rectified.png: a classroom/lab seen by the author's 640x480 stereo rig, rectified
#     by the author (curved black borders). Indoor.
set -euo pipefail
DEST=${1:?usage: fetch_valset.sh DEST MIRROR_ROOT}; M=${2:?MIRROR_ROOT: the folder that holds the fetched snapshots, one <owner>+<name>/ each}
cp1() { # gitdir commit srcpath dstpath
  mkdir -p "$(dirname "$4")"; git --git-dir "$1" show "$2:$3" > "$4"; }

# A. DrivingStereo (12 pairs, JPEG kept as .jpg)
G=$M/jedld+usam-net-inference/repo; C=36c8f2ec56144e986e00d9172a66bc983bfdcf86; D=$DEST/driving_usam-net-inference
for src in \
  sample:2018-10-11-16-03-19_2018-10-11-16-58-57-454 \
  sample:2018-10-19-10-33-08_2018-10-19-11-06-02-333 \
  sample:2018-07-11-14-48-52_2018-07-11-14-50-22-775 \
  data/test:2018-07-11-14-48-52_2018-07-11-14-50-08-769 \
  data/test:2018-07-11-14-48-52_2018-07-11-14-50-09-270 \
  data/test:2018-07-11-14-48-52_2018-07-11-14-50-10-370 \
  data/test:2018-07-11-14-48-52_2018-07-11-14-50-11-468 \
  data/test:2018-07-11-14-48-52_2018-07-11-14-50-12-268 \
  data/train:2018-07-09-16-11-56_2018-07-09-16-11-56-502 \
  data/train:2018-07-09-16-11-56_2018-07-09-16-11-57-301 \
  data/train:2018-07-09-16-11-56_2018-07-09-16-11-58-603 \
  data/train:2018-07-09-16-11-56_2018-07-09-16-11-59-605; do
  dir=${src%%:*}; n=${src#*:}
  cp1 $G $C $dir/left_images/$n.jpg  $D/image_2/$n.jpg
  cp1 $G $C $dir/right_images/$n.jpg $D/image_3/$n.jpg
done

# B. ETH3D two-view training (10 pairs)
G=$M/ccj5351+ccj5351.github.io/repo; C=34f515936a401a585a307494e9237cf1a3aa6fd5; D=$DEST/nondriving_eth3d_ccj5351
P=files/stereo-datasets/ETH3D/two_view_training
for n in delivery_area_1l electro_1l electro_3s facade_1s forest_2s playground_1l playground_3s terrace_2s \
         terrains_1l terrains_2s; do
  cp1 $G $C $P/image_0/$n.png $D/image_2/$n.png
  cp1 $G $C $P/image_1/$n.png $D/image_3/$n.png
done

# C + D. single indoor pairs
D=$DEST/indoor_misc
G=$M/srikanthmalla+stereo/repo; C=28fa95963ec870577b280deb05d4db12c5b450de
cp1 $G $C left_rectified.png  $D/image_2/euroc_vicon_room.png
cp1 $G $C right_rectified.png $D/image_3/euroc_vicon_room.png
G=$M/dhaivat1729+ego_motion_pt_cloud/repo; C=dae1383f2ada81c890ee8493c466f77d112dffa7
cp1 $G $C left_rectified.png  $D/image_2/classroom_dhaivat.png
cp1 $G $C right_rectified.png $D/image_3/classroom_dhaivat.png
echo done

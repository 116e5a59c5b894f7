"""ETH3D two-view (low-res) stereo in its official layout: the images and GT come as separate archives.

Layout under ``root`` (as RAFT-Stereo and most stereo code unpack the archives)::

    two_view_training/<scene>/im0.png, im1.png, calib.txt      (two_view_training.7z)
    two_view_training_gt/<scene>/disp0GT.pfm, mask0nocc.png    (two_view_training_gt.7z)
    two_view_test/<scene>/im0.png, im1.png, calib.txt          (two_view_test.7z; ``two_view_testing`` accepted)

The GT files may also lie in the scene folder itself (both archives unpacked into one folder); ``root`` may also be
a folder of scene folders, or one scene folder. GT: ``disp0GT.pfm`` float32 px of the left view (im0), inf = unknown;
``mask0nocc.png`` 255 = non-occluded (-> ``gt_noc``), other values (128 occluded, 0 no GT) are left out of it;
``calib.txt`` (Middlebury's key=value format) gives ``ndisp`` -> ``max_disp`` when present. ETH3D has no right-view
GT. Frame ids are the scene names (``delivery_area_1l``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pvm_labeler.common.datasets.refs import PairRef, _first_existing, _require_dir, _safe_id
from pvm_labeler.common.errors import InputError

#: Image folder names of each split, in the order they are looked for.
ETH3D_SPLIT_FOLDERS: dict[str, tuple[str, ...]] = {"training": ("two_view_training",),
                                                   "testing": ("two_view_test", "two_view_testing")}
ETH3D_GT_FOLDER = "two_view_training_gt"


def _scene_folders(base: Path) -> list[Path]:
    if (base / "im0.png").is_file():
        return [base]
    return sorted(p for p in base.iterdir() if p.is_dir() and (p / "im0.png").is_file())


def _eth3d_ref(scene: Path, gt_root: Path) -> PairRef:
    left, right = scene / "im0.png", scene / "im1.png"
    if not right.is_file():
        raise InputError(f"eth3d: left image {left} has no right image {right}")
    gt_dir = next((d for d in (gt_root / scene.name, scene) if (d / "disp0GT.pfm").is_file()), None)
    meta: dict[str, Any] = {"dataset": "eth3d", "gt_format": "pfm"}
    if gt_dir is not None and (gt_dir / "mask0nocc.png").is_file():
        meta["noc_mask"] = str(gt_dir / "mask0nocc.png")
    calib = _first_existing(scene / "calib.txt")
    if calib is not None:
        meta["calib"] = str(calib)
    gt = None if gt_dir is None else gt_dir / "disp0GT.pfm"
    return PairRef(frame_id=_safe_id(scene.name), left=left, right=right, gt=gt, meta=meta)


def _discover_eth3d(root: Path, split: str, **_: Any) -> list[PairRef]:
    _require_dir(root, "eth3d root")
    base = next((root / n for n in ETH3D_SPLIT_FOLDERS[split] if (root / n).is_dir()), None)
    if base is None:
        if any((root / n).is_dir() for names in ETH3D_SPLIT_FOLDERS.values() for n in names):
            raise InputError(f"eth3d split folder for '{split}' not found under {root} (expected "
                             f"{' or '.join(ETH3D_SPLIT_FOLDERS[split])})")
        base = root  # a folder of scene folders, or one scene
    return [_eth3d_ref(scene, root / ETH3D_GT_FOLDER) for scene in _scene_folders(base)]

"""The distillation pack: every unlabelled training pair of ../shared/data as one JPEG ``folder`` dataset.

kitti_unlabelled (87 pairs) and each sub-folder of unlabelled_more (57 pairs) go to ``OUT/{left,right}/<set>_<id>.jpg``
at JPEG quality 92: ~44 MB, which with the tracked tree fits the lent GPU's 64 MiB carry (PNG: 200 MB). No GT file is
read or copied. Used by ``pipelines/studies/gpu/distill.sh``:

    python -m pipelines.studies.gpu.distill_pack .carry/distill
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
from tqdm import tqdm

from pvm_labeler.common.datasets import discover
from pvm_labeler.common.errors import InputError
from pvm_labeler.common.io import read_image

SHARED = Path("../shared/data")
QUALITY = 92


def training_sets(shared: Path) -> list[tuple[str, str, Path, dict[str, str]]]:
    """(prefix, reader, root, reader options) of every unlabelled training folder under ``shared``."""
    sets = [("ku", "kitti_unlabelled", shared / "kitti_unlabelled", {})]
    for folder in sorted(p for p in (shared / "unlabelled_more").iterdir() if p.is_dir()):
        sets.append((f"um_{folder.name}", "folder", folder, {"left": "image_2", "right": "image_3"}))
    return sets


def write_pack(shared: Path, out: Path, quality: int = QUALITY) -> int:
    """Write every pair of :func:`training_sets` as JPEG into ``out/left`` and ``out/right``; returns the pairs."""
    for view in ("left", "right"):
        (out / view).mkdir(parents=True, exist_ok=True)
    refs = [(prefix, ref) for prefix, reader, root, kw in training_sets(shared) for ref in discover(reader, root, **kw)]
    for prefix, ref in tqdm(refs, desc="pack", unit="pair"):
        for view, path in (("left", ref.left), ("right", ref.right)):
            target = out / view / f"{prefix}_{ref.frame_id}.jpg"
            bgr = cv2.cvtColor(read_image(path), cv2.COLOR_RGB2BGR)
            if not cv2.imwrite(str(target), bgr, [cv2.IMWRITE_JPEG_QUALITY, quality]):
                raise InputError(f"cannot write {target}")
    return len(refs)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--shared", type=Path, default=SHARED)
    parser.add_argument("--quality", type=int, default=QUALITY)
    args = parser.parse_args(argv)
    print(f"{write_pack(args.shared, args.out, args.quality)} pairs -> {args.out}")


if __name__ == "__main__":
    main()

"""Copy a dataset's image pairs as a small ``folder`` dataset, for a machine with a transfer budget (a lent GPU box).

The 87 unlabelled KITTI pairs are 135 MB of PNG; as JPEG q95 they are ~33 MB, under the GPU box's 64 MiB carry.
Their labels are 16-bit PNGs of noisy sub-pixel values (~0.5 MB per view), so they are cheaper to recompute there
(``pvm-label run --dataset folder --root PACK --compression lzf``: 16 cores, no hdf5plugin) than to carry. Measured on
the 15 KITTI 2015 GT frames: PVM labels of JPEG q95 copies cover 58.0 % of GT pixels at 1.08 % bad-3, against
60.1 % and 1.02 % from the PNGs; a network trained there trains on JPEG-decoded images, which its report says.

    python -m pipelines.studies.carry_pack --dataset kitti_unlabelled --root ../shared/data/kitti_unlabelled .carry/unl
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
from tqdm import tqdm

from pvm_labeler.common.datasets import discover
from pvm_labeler.common.errors import InputError
from pvm_labeler.common.io import read_image


def write_jpeg_folder(dataset: str, root: Path | None, out: Path, quality: int = 95) -> int:
    """Write ``out/left/<frame id>.jpg`` and ``out/right/<frame id>.jpg`` for every pair; returns the pair count.

    GT files are never copied: the pack is training input only.
    """
    refs = discover(dataset, root)
    for view in ("left", "right"):
        (out / view).mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)]
    for ref in tqdm(refs, desc="jpeg", unit="pair"):
        for view, path in (("left", ref.left), ("right", ref.right)):
            target = out / view / f"{ref.frame_id}.jpg"
            if not cv2.imwrite(str(target), cv2.cvtColor(read_image(path), cv2.COLOR_RGB2BGR), params):
                raise InputError(f"cannot write {target}")
    return len(refs)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("out", type=Path)
    parser.add_argument("--dataset", default="kitti_unlabelled")
    parser.add_argument("--root", type=Path)
    parser.add_argument("--quality", type=int, default=95)
    args = parser.parse_args(argv)
    n = write_jpeg_folder(args.dataset, args.root, args.out, args.quality)
    print(f"{n} pairs -> {args.out}")


if __name__ == "__main__":
    main()

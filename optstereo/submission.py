"""KITTI benchmark submissions: ``optstereo-predict --submission`` zips ``disp_0/<frame>_10.png`` and checks it."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pvm_labeler.common.atomic import atomic_path
from pvm_labeler.common.io import image_size

__all__ = ["BENCHMARK_FRAMES", "submission_problems", "write_submission"]

#: The reference frames of each KITTI benchmark's testing split, which its server scores.
BENCHMARK_FRAMES = {"kitti15": 200, "kitti12": 195}


def write_submission(pred_dir: Path, zip_path: Path, refs: list[Any]) -> Path:
    """Zip ``pred_dir/disp_0/<frame>_10.png`` into a KITTI benchmark submission and check it before returning.

    Only the reference frames (``_10``) are submitted. The check re-reads every entry: a 16-bit PNG at its own
    image's size (KITTI mixes 1242x375, 1241x376, 1224x370, ...), one per frame, nothing else in the archive.

    Raises:
        ValueError: naming the frame whose file is missing, of another size or not 16-bit.
    """
    frames = sorted((r for r in refs if r.frame_id.endswith("_10")), key=lambda r: r.frame_id)
    if not frames:
        raise ValueError("no reference frames (<id>_10) to submit")
    zip_path = Path(zip_path)
    with atomic_path(zip_path) as tmp:
        _write_checked_zip(tmp, zip_path, frames, pred_dir)
    return zip_path


def _write_checked_zip(tmp: Path, zip_path: Path, frames: list, pred_dir: Path) -> None:
    """Write the submission entries to ``tmp`` and re-read them as the server will."""
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
        for ref in frames:
            src = Path(pred_dir) / "disp_0" / f"{ref.frame_id}.png"
            if not src.is_file():
                raise ValueError(f"submission: prediction for frame {ref.frame_id} missing: {src}")
            zf.write(src, f"disp_0/{ref.frame_id}.png")
    with zipfile.ZipFile(tmp) as zf:  # check what was written, as the server will read it
        names = sorted(zf.namelist())
        expected = sorted(f"disp_0/{r.frame_id}.png" for r in frames)
        if names != expected:
            raise ValueError(f"submission {zip_path}: entries {names[:3]}... differ from the frames {expected[:3]}...")
        for ref in frames:
            raw = cv2.imdecode(np.frombuffer(zf.read(f"disp_0/{ref.frame_id}.png"), np.uint8), cv2.IMREAD_UNCHANGED)
            want = image_size(ref.left)
            if raw is None or raw.dtype != np.uint16 or raw.shape != want:
                got = None if raw is None else (raw.shape, raw.dtype)
                raise ValueError(f"submission: frame {ref.frame_id} is {got}, expected uint16 of size {want}")


def submission_problems(dataset: str, split: str, frames: int) -> list[str]:
    """Why KITTI's server would refuse a submission of ``frames`` reference frames of ``dataset``'s ``split`` that
    is well formed (:func:`write_submission` checks the files): not the testing split, another frame count."""
    problems = []
    if split != "testing":
        problems.append(f"it holds the {split!r} split's frames; the server scores the testing split's "
                        "(--split testing)")
    want = BENCHMARK_FRAMES.get(dataset)
    if want is not None and frames != want:
        problems.append(f"it holds {frames} frames; {dataset}'s testing split has {want} (a --limit, or another "
                        "folder)")
    return problems

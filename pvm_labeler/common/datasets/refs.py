"""Pair records (paths only) and decoded samples, plus the small path helpers every reader uses."""

from __future__ import annotations

import hashlib
import logging
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from pvm_labeler.common.errors import InputError

logger = logging.getLogger(__name__)

DATASETS: tuple[str, ...] = ("kitti15", "kitti12", "middlebury", "eth3d", "sceneflow", "folder", "kitti_unlabelled",
                             "sample")
SPLITS: tuple[str, ...] = ("training", "testing")
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".webp", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")

#: Search range that comfortably covers a dataset when the user gives no --max-disp (sample GT max is 59.9 px).
DEFAULT_MAX_DISP: dict[str, int] = {"sample": 64}


#: PairRef.meta entries that name files (a noc mask, an occlusion map, a calibration with the search range).
META_FILES: tuple[str, ...] = ("noc_mask", "occlusion", "calib")


@dataclass
class PairRef:
    """Where one stereo pair lives on disk (cheap to create, picklable, JSON-able through :meth:`to_dict`).

    Attributes:
        frame_id: stable unique id within the dataset (also the HDF5 group name; contains no "/").
        left, right: image files.
        gt: most complete left-view GT file (occ/all if present, else noc), or None.
        gt_noc: non-occluded left GT file (or None).
        gt_right: right-view GT file (or None).
        meta: dataset name, GT decoding ("gt_format", "gt_scale"), extra files (noc masks, calib) as strings.
    """

    frame_id: str
    left: Path
    right: Path
    gt: Path | None = None
    gt_noc: Path | None = None
    gt_right: Path | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable description (paths as strings)."""
        out: dict[str, Any] = {"frame_id": self.frame_id, "left": str(self.left), "right": str(self.right)}
        for name in ("gt", "gt_noc", "gt_right"):
            value = getattr(self, name)
            if value is not None:
                out[name] = str(value)
        out["meta"] = dict(self.meta)
        return out

    def source_digest(self) -> str:
        """16 hex digits of BLAKE2b over the bytes of the pair's files (images, GT maps and the meta files that
        shape a sample: noc mask, occlusion, calib; by role, a role without a file counting as such), so a resumed
        job sees a file replaced under the same name."""
        digest = hashlib.blake2b(digest_size=8)
        for role in ("left", "right", "gt", "gt_noc", "gt_right", *META_FILES):
            path = self.meta.get(role) if role in META_FILES else getattr(self, role)
            digest.update(role.encode())
            if path is not None and Path(path).is_file():
                with open(path, "rb") as fh:
                    for block in iter(lambda: fh.read(1 << 20), b""):
                        digest.update(block)
            else:
                digest.update(b"\0none")
        return digest.hexdigest()


@dataclass
class StereoSample:
    """One decoded stereo pair.

    Attributes:
        frame_id: id from the :class:`PairRef`.
        left, right: (H, W, 3) uint8 RGB.
        gt: (H, W) float32 most complete left GT (occ/all if present, else noc), NaN = unknown; None if absent.
        gt_noc: (H, W) float32 non-occluded left GT (KITTI disp_noc, Middlebury mask0nocc == 255, Scene Flow
            occlusion == False), NaN elsewhere; None if the dataset has no occlusion information.
        gt_right: (H, W) float32 right-view GT (right(x) matches left(x + d)), NaN = unknown; None if absent.
        sources: file paths used, by role.
        max_disp: dataset hint for the search range (MiddEval3 / ETH3D calib ndisp), else None.
    """

    frame_id: str
    left: npt.NDArray[np.uint8]
    right: npt.NDArray[np.uint8]
    gt: npt.NDArray[np.float32] | None
    gt_noc: npt.NDArray[np.float32] | None
    gt_right: npt.NDArray[np.float32] | None
    sources: dict[str, str]
    max_disp: int | None = None


# --------------------------------------------------------------------------------------------------- helpers
def _require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise InputError(f"{what} not found: {path} (expected a directory)")
    return path


def _images_in(folder: Path) -> dict[str, Path]:
    """stem -> image path for every image file directly inside ``folder``; hidden files (``.x.png``, macOS's ``._x.png``
    resource forks) are no images of the dataset, as a glob's ``*`` leaves them out too."""
    return by_stem([p for p in sorted(folder.iterdir())
                    if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")], str(folder))


def by_stem(files: list[Path], where: str, key: Callable[[Path], str] | None = None) -> dict[str, Path]:
    """stem (or ``key(path)``) -> path of ``files``; InputError naming the files when two share one (0000.png and
    0000.jpg, or the same name in two folders a glob spans): which of them is the view would be a guess."""
    out: dict[str, Path] = {}
    clashes: list[str] = []
    for path in files:
        name = path.stem if key is None else key(path)
        if name in out:
            clashes.append(f"{out[name]} and {path}")
        out.setdefault(name, path)
    if clashes:
        more = f" (and {len(clashes) - 3} more)" if len(clashes) > 3 else ""
        raise InputError(f"{where}: images share a name, so which is the view cannot be told: "
                         f"{'; '.join(clashes[:3])}{more}; keep one image per name")
    return out


def _check_counts(left: dict[str, Path], right: dict[str, Path], left_dir: Path, right_dir: Path) -> None:
    missing_right = sorted(set(left) - set(right))
    missing_left = sorted(set(right) - set(left))
    if missing_right or missing_left:
        raise InputError(
            f"left/right count mismatch: {len(left)} images in {left_dir} vs {len(right)} in {right_dir}; "
            f"no right image for {[str(left[s]) for s in missing_right[:5]]}, "
            f"no left image for {[str(right[s]) for s in missing_left[:5]]}"
        )


def _first_existing(*candidates: Path) -> Path | None:
    for path in candidates:
        if path.is_file():
            return path
    return None


def _safe_id(text: str) -> str:
    """Make a string usable as an HDF5 group name and file-system friendly ("/" separates HDF5 groups); letters and
    digits of any script stay (日本 and 東京 both became "frame", a clash that stopped the run)."""
    text = re.sub(r"[^\w.+-]+", "-", text).strip("-.")
    return text or "frame"


def safe_stem(frame_id: str) -> str:
    """``frame_id`` as the stem of a file written (or read) inside one output folder: unchanged when it is a plain
    name, else made one by the readers' own rule (:func:`_safe_id`), with a warning naming both.

    The readers' ids are plain names already; a shard's ids come from its file and its ``index.json``, which anyone
    can write: ``../../x`` or ``/abs/x`` must not lead a map or a disparity file out of its folder.
    """
    text = str(frame_id)
    if text not in ("", ".", "..") and not any(sep in text for sep in ("/", "\\", "\0")):
        return text
    stem = _safe_id(text)
    logger.warning("frame id %r is no plain file name: its files are named %r", text, stem)
    return stem



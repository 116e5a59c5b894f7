"""Discovery of pairs in each dataset's official layout (KITTI, Middlebury, Scene Flow, folders, unlabelled KITTI)."""

from __future__ import annotations

import glob as globlib
import logging
import re
from pathlib import Path
from typing import Any

from pvm_labeler.common import io
from pvm_labeler.common.datasets.refs import (
    IMAGE_SUFFIXES,
    PairRef,
    _check_counts,
    _first_existing,
    _images_in,
    _require_dir,
    _safe_id,
    by_stem,
)
from pvm_labeler.common.errors import InputError, counted

logger = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------------------ KITTI
def _discover_kitti(root: Path, split: str, left: str, right: str, occ: str, noc: str, name: str) -> list[PairRef]:
    base = _require_dir(root / split, f"{name} split folder '{split}'")
    left_dir = _require_dir(base / left, f"{name} left image folder")
    right_dir = _require_dir(base / right, f"{name} right image folder")
    lefts, rights = _images_in(left_dir), _images_in(right_dir)
    _check_counts(lefts, rights, left_dir, right_dir)
    occ_dir, noc_dir = base / occ, base / noc
    refs = []
    for stem in sorted(lefts):
        gt_occ = _first_existing(occ_dir / f"{stem}.png")
        gt_noc = _first_existing(noc_dir / f"{stem}.png")
        refs.append(
            PairRef(
                frame_id=_safe_id(stem),
                left=lefts[stem],
                right=rights[stem],
                gt=gt_occ or gt_noc,  # most complete first; frames with only disp_noc keep gt = noc
                gt_noc=gt_noc,
                meta={"dataset": name, "gt_format": "kitti"},
            )
        )
    return refs


def _discover_kitti15(root: Path, split: str, **_: Any) -> list[PairRef]:
    return _discover_kitti(root, split, "image_2", "image_3", "disp_occ_0", "disp_noc_0", "kitti15")


def _discover_kitti12(root: Path, split: str, **_: Any) -> list[PairRef]:
    return _discover_kitti(root, split, "colored_0", "colored_1", "disp_occ", "disp_noc", "kitti12")


# -------------------------------------------------------------------------------------------------- Middlebury
#: GT scale of the 2005 / 2006 layout: it depends on the image size, see :func:`middlebury_2005_scale`.
BY_SIZE = "by size"
# (left, right, left GT, right GT, GT scale) per layout; scale None = PFM with inf = unknown.
_MIDDLEBURY_LAYOUTS: tuple[tuple[str, str, str, str, float | str | None], ...] = (
    ("im0.png", "im1.png", "disp0GT.pfm", "disp1GT.pfm", None),  # MiddEval3 / 2014
    ("im2.png", "im6.png", "disp2.png", "disp6.png", 4.0),  # 2003 (cones, teddy), quarter size
    ("im2.ppm", "im6.ppm", "disp2.pgm", "disp6.pgm", 8.0),  # 2001 (venus, sawtooth, ...)
    ("im2.png", "im6.png", "disp2.pgm", "disp6.pgm", 8.0),
    ("im3.png", "im4.png", "disp3.pgm", "disp4.pgm", 16.0),  # 2001 tsukuba (truedisp scaled by 16)
    ("im3.ppm", "im4.ppm", "disp3.pgm", "disp4.pgm", 16.0),
    ("view1.png", "view5.png", "disp1.png", "disp5.png", BY_SIZE),  # 2005 (Art, ...) / 2006 (Aloe, ...)
)
#: Middlebury 2005 / 2006: every size's 8-bit disparity maps hold the value of the full-size images (1 unit = 1
#: full-size pixel), so the disparity of a map's own images is value / 1 (FullSize, 1110 rows), value / 2
#: (HalfSize, 555 rows) or value / 3 (ThirdSize, 370 rows). The release folders are named by size.
MIDDLEBURY_2005_SIZES: dict[str, tuple[int, float]] = {"FullSize": (1110, 1.0), "HalfSize": (555, 2.0),
                                                       "ThirdSize": (370, 3.0)}


def middlebury_2005_scale(left: Path) -> float:
    """The GT divisor of a Middlebury 2005 / 2006 pair, from the size folder in its path (FullSize / HalfSize /
    ThirdSize) or, without one, from the image height (1110 / 555 / 370 rows, the heights of every scene).

    Raises:
        InputError: the height is none of the three and no size folder names it, or the two disagree.
    """
    height = io.image_size(left)[0]
    by_height = {rows: (name, scale) for name, (rows, scale) in MIDDLEBURY_2005_SIZES.items()}
    folder = next((p for p in reversed(left.parts) if p in MIDDLEBURY_2005_SIZES), None)
    if folder is not None:
        rows, scale = MIDDLEBURY_2005_SIZES[folder]
        if height in by_height and height != rows:
            raise InputError(f"middlebury 2005/2006: {left} lies in a {folder} folder ({rows} rows) but has "
                             f"{height} rows, the height of {by_height[height][0]}; which size is it?")
        return scale
    if height not in by_height:
        raise InputError(f"middlebury 2005/2006: cannot tell the size of {left} (its GT scale depends on it): "
                         f"{height} rows is none of 1110 / 555 / 370 (FullSize / HalfSize / ThirdSize) and no "
                         "folder of its path is named FullSize, HalfSize or ThirdSize")
    return by_height[height][1]


def _middlebury_2005_gt(folder: Path, name: str) -> Path | None:
    """A 2005 / 2006 GT map beside the views (the 2-view archives), else two levels up (``<scene>/Illum<i>/Exp<e>/``
    views of the full archives, whose GT lies in ``<scene>/``)."""
    beside = _first_existing(folder / name)
    if beside is not None or not (folder.name.startswith("Exp") and folder.parent.name.startswith("Illum")):
        return beside
    return _first_existing(folder.parent.parent / name)


def read_middlebury_calib(path: Path) -> dict[str, str]:
    """Parse a MiddEval3 ``calib.txt`` (``key=value`` lines) into a dict of strings."""
    values = {}
    for line in path.read_text().splitlines():
        if "=" in line:
            key, value = line.split("=", 1)
            values[key.strip()] = value.strip()
    return values


def _middlebury_ref(folder: Path, root: Path) -> PairRef | None:
    for left_name, right_name, gt_name, gt_right_name, scale in _MIDDLEBURY_LAYOUTS:
        left, right = folder / left_name, folder / right_name
        if not left.is_file():
            continue
        if not right.is_file():
            raise InputError(f"middlebury: left image {left} has no right image {right}")
        rel = folder.relative_to(root).as_posix()
        meta: dict[str, Any] = {"dataset": "middlebury", "gt_format": "pfm" if scale is None else "scaled"}
        gt, gt_right = _first_existing(folder / gt_name), _first_existing(folder / gt_right_name)
        if scale == BY_SIZE:
            gt, gt_right = _middlebury_2005_gt(folder, gt_name), _middlebury_2005_gt(folder, gt_right_name)
            scale = middlebury_2005_scale(left) if gt is not None or gt_right is not None else None
        if scale is not None:
            meta["gt_scale"] = scale
        mask = folder / "mask0nocc.png"
        if scale is None and mask.is_file():
            meta["noc_mask"] = str(mask)
        calib = folder / "calib.txt"
        if calib.is_file():
            meta["calib"] = str(calib)
        return PairRef(
            frame_id=_safe_id(folder.name if rel == "." else rel),
            left=left,
            right=right,
            gt=gt,
            gt_noc=None,
            gt_right=gt_right,
            meta=meta,
        )
    return None


def _discover_middlebury(root: Path, split: str, **_: Any) -> list[PairRef]:
    # The Middlebury releases have no common split folder names (trainingQ, 2003 scenes ...), so every folder
    # under root that holds a known pair is a frame; `split` is ignored (documented).
    _require_dir(root, "middlebury root")
    folders = [root, *sorted(p for p in root.rglob("*") if p.is_dir())]
    refs = [ref for ref in (_middlebury_ref(f, root) for f in folders) if ref is not None]
    return refs


# --------------------------------------------------------------------------------------------------- SceneFlow
_PASS_DIR = re.compile(r"^(frames|RGB)_(clean|final)pass$")


def _discover_sceneflow(root: Path, split: str, pass_: str = "clean", **_: Any) -> list[PairRef]:
    _require_dir(root, "sceneflow root")
    wanted = {"training": "TRAIN", "testing": "TEST"}[split]
    pass_dirs = sorted(
        p for p in [root, *root.rglob("*")] if p.is_dir() and (m := _PASS_DIR.match(p.name)) and m.group(2) == pass_
    )
    refs = []
    for pass_dir in pass_dirs:
        base = pass_dir.parent
        for left in sorted(pass_dir.rglob("left/*.png")):
            rel = left.parent.parent.relative_to(pass_dir)
            parts = rel.parts
            # FlyingThings3D has TRAIN/TEST folders; other subsets (Driving, Monkaa, flat copies) have no split.
            if any(p in ("TRAIN", "TEST") for p in parts) and wanted not in parts:
                continue
            right = left.parent.parent / "right" / left.name
            if not right.is_file():
                raise InputError(f"sceneflow: left image {left} has no right image {right}")
            disp_dir = base / "disparity" / rel
            occ = base / "occlusion" / rel / "left" / left.name
            meta: dict[str, Any] = {"dataset": "sceneflow", "gt_format": "pfm"}
            if occ.is_file():
                meta["occlusion"] = str(occ)
            id_parts = [*base.relative_to(root).parts, *parts, left.stem]
            refs.append(
                PairRef(
                    frame_id=_safe_id("-".join(id_parts)),
                    left=left,
                    right=right,
                    gt=_first_existing(disp_dir / "left" / f"{left.stem}.pfm"),
                    gt_right=_first_existing(disp_dir / "right" / f"{left.stem}.pfm"),
                    meta=meta,
                )
            )
    return refs


# ------------------------------------------------------------------------------------------------------ folder
_WILDCARD = re.compile(r"[*?\[]")


def _image_files(spec: str | Path, root: Path | None, what: str) -> tuple[list[Path], Path, bool]:
    """(image files, the spec as a path under ``root``, whether it is a glob) of a --left/--right value: a folder's
    images, or a glob's (``**`` spans any depth of folders)."""
    spec = Path(spec)
    if root is not None and not spec.is_absolute():
        spec = root / spec
    if spec.is_dir():
        return list(_images_in(spec).values()), spec, False
    if _WILDCARD.search(str(spec)):
        files = sorted(Path(p) for p in globlib.glob(str(spec), recursive=True)
                       if Path(p).suffix.lower() in IMAGE_SUFFIXES)
        return files, spec, True
    raise InputError(f"folder dataset: {what} '{spec}' is neither a directory nor a glob pattern that exists"
                     + _layout_hint(root))


def glob_key(path: Path, pattern: Path) -> str:
    """The name of an image a glob found, with the folders its wildcards matched: ``seq1/0001`` for
    ``seq1/left/0001.png`` under ``*/left/*.png`` (the pattern's literal folders, here ``left``, dropped), so that
    the left and right views of one frame get one name across sequences whose files share names."""
    parts = pattern.parts
    fixed = next((i for i, part in enumerate(parts) if _WILDCARD.search(part)), len(parts))
    literal = {part for part in parts[fixed:-1] if not _WILDCARD.search(part)}
    folders = [part for part in path.parts[fixed:-1] if part not in literal]
    return "/".join([*folders, path.stem])


def _keyed_views(left: str | Path, right: str | Path, root: Path | None
                 ) -> tuple[dict[str, Path], dict[str, Path], str, str]:
    """(left name -> file, right name -> file, left spec, right spec). Names are file stems; when a glob finds two
    images of one stem on either side (sequences in folders of their own), every glob's images are named by
    :func:`glob_key` instead (a folder's by their stems).

    Raises:
        InputError: a spec that is neither a folder nor a glob; two images of one name on a side all the same
            (0000.png beside 0000.jpg).
    """
    (left_files, left_spec, left_glob), (right_files, right_spec, right_glob) = (
        _image_files(left, root, "left"), _image_files(right, root, "right"))
    by_folder = any(is_glob and len({p.stem for p in files}) < len(files)
                    for files, is_glob in ((left_files, left_glob), (right_files, right_glob)))

    def keyed(files: list[Path], spec: Path, is_glob: bool) -> dict[str, Path]:
        return by_stem(files, str(spec), (lambda path: glob_key(path, spec)) if by_folder and is_glob else None)

    return (keyed(left_files, left_spec, left_glob), keyed(right_files, right_spec, right_glob), str(left_spec),
            str(right_spec))


#: Left / right folder names of common layouts (KITTI, KITTI raw, EuRoC-style rigs), for the hint of a miss.
KNOWN_VIEW_FOLDERS = (("image_2", "image_3"), ("image_02", "image_03"), ("image_0", "image_1"), ("cam0", "cam1"))


def _layout_hint(root: Path | None) -> str:
    """"; it holds image_2/ and image_3/: give --left image_2 --right image_3" when ``root`` holds a known pair of
    view folders (the default left/ and right/ missing), else the (first six) sub-folders holding images, else ""."""
    if root is None or not root.is_dir():
        return ""
    for left, right in KNOWN_VIEW_FOLDERS:
        if (root / left).is_dir() and (root / right).is_dir():
            return f"; {root} holds {left}/ and {right}/: give --left {left} --right {right}"
    with_images = sorted(p.name for p in root.iterdir() if p.is_dir() and any(
        f.suffix.lower() in IMAGE_SUFFIXES for f in p.iterdir() if f.is_file()))
    if with_images:
        return f"; folders of images in {root}: {', '.join(n + '/' for n in with_images[:6])}: give --left and --right"
    return ""


def _few(paths: list[Path], limit: int = 5) -> str:
    """``paths`` for an error message: the first ``limit`` as strings, then how many more there are."""
    shown = ", ".join(str(p) for p in paths[:limit])
    return shown + (f" and {len(paths) - limit} more" if len(paths) > limit else "")


def _folder_pairs(lefts: dict[str, Path], rights: dict[str, Path], left_spec: str,
                  right_spec: str) -> list[tuple[str, Path, Path]]:
    """(frame stem, left, right) of every pair: by stem; by sorted order (with a warning) only when no stem is
    shared and the counts match (rigs that name the views cam0_0001 / cam1_0001).

    Raises:
        InputError: no images at all, or some images have no partner (naming a few of them, their count and the
            folders).
    """
    if not lefts and not rights:
        raise InputError(f"folder dataset: no images found: left '{left_spec}' and right '{right_spec}' hold no "
                         f"{'/'.join(IMAGE_SUFFIXES)} files (set --left / --right, folders or globs)")
    shared = sorted(set(lefts) & set(rights))
    if not shared and len(lefts) == len(rights):
        left_keys, right_keys = sorted(lefts), sorted(rights)
        logger.warning("folder dataset: no left image in %s has the name of a right image in %s: paired the %d "
                       "images by sorted order (first pair %s + %s); check that this is what you want",
                       left_spec, right_spec, len(lefts), lefts[left_keys[0]].name, rights[right_keys[0]].name)
        return [(lk, lefts[lk], rights[rk]) for lk, rk in zip(left_keys, right_keys, strict=True)]
    lonely_left = [lefts[s] for s in sorted(set(lefts) - set(rights))]
    lonely_right = [rights[s] for s in sorted(set(rights) - set(lefts))]
    if lonely_left or lonely_right:
        what = "count mismatch" if len(lefts) != len(rights) else "names do not pair up"
        details = [f"{counted(len(shared), 'name')} in common"]
        if lonely_left:
            details.append(f"{counted(len(lonely_left), 'left image')} without a right image of the same name: "
                           f"{_few(lonely_left)}")
        if lonely_right:
            details.append(f"{counted(len(lonely_right), 'right image')} without a left image of the same name: "
                           f"{_few(lonely_right)}")
        if any("/" in name for name in [*lefts, *rights]):
            details.append("images a glob finds in folders of their own are named by those folders too (seq1/0001 "
                           "for seq1/left/0001.png under */left/*.png), as two images of one name were found")
        raise InputError(f"folder dataset: left/right {what}: {counted(len(lefts), 'image')} in {left_spec} vs "
                         f"{len(rights)} in {right_spec}; " + "; ".join(details))
    return [(stem, lefts[stem], rights[stem]) for stem in shared]


def _discover_folder(
    root: Path | None,
    split: str,
    left: str | Path = "left",
    right: str | Path = "right",
    gt: str | Path | None = None,
    gt_scale: float = io.KITTI_SCALE,
    **_: Any,
) -> list[PairRef]:
    lefts, rights, left_spec, right_spec = _keyed_views(left, right, root)
    pairs = _folder_pairs(lefts, rights, left_spec, right_spec)
    gts: dict[str, Path] = {}
    if gt is None and root is not None and (root / "gt").is_dir():
        gt = "gt"
    if gt is not None:
        if any("/" in name for name in lefts):
            raise InputError(f"folder dataset: --gt is one folder of names, but the views' globs span folders whose "
                             f"images share names ({_few([Path(n) for n in list(lefts)[:5]])}): give one "
                             "sequence at a time with its GT folder")
        gt_path = Path(gt) if root is None or Path(gt).is_absolute() else root / gt
        _require_dir(gt_path, "folder dataset GT folder")
        gts = {p.stem: p for p in sorted(gt_path.iterdir()) if p.suffix.lower() in (".png", ".pfm", ".npy")}
    refs = []
    for stem, lpath, rpath in pairs:
        gpath = gts.get(stem)
        meta: dict[str, Any] = {"dataset": "folder"}
        if gpath is not None:
            meta.update(_gt_format_for(gpath, gt_scale))
        refs.append(PairRef(frame_id=_safe_id(stem), left=lpath, right=rpath, gt=gpath, meta=meta))
    return refs


def _gt_format_for(path: Path, scale: float) -> dict[str, Any]:
    suffix = path.suffix.lower()
    if suffix == ".pfm":
        return {"gt_format": "pfm"}
    if suffix == ".npy":
        return {"gt_format": "npy"}
    return {"gt_format": "scaled", "gt_scale": float(scale)}


# ------------------------------------------------------------------------------------------- KITTI, no GT
#: (left, right) image-folder names of the KITTI layouts found in the wild (stereo 2012/2015, odometry, raw).
_UNLABELLED_FOLDERS: tuple[tuple[str, str], ...] = (("image_2", "image_3"), ("image_02", "image_03"),
                                                   ("colored_0", "colored_1"))


def _unlabelled_pairs(folder: Path, root: Path) -> list[PairRef]:
    """The pairs directly under ``folder``: KITTI view folders (or their ``data/``), or left.png + right.png."""
    prefix = "" if folder == root else str(folder.relative_to(root)) + "-"
    meta = {"dataset": "kitti_unlabelled"}
    for left_name, right_name in _UNLABELLED_FOLDERS:
        left_dir, right_dir = folder / left_name, folder / right_name
        if (left_dir / "data").is_dir() and (right_dir / "data").is_dir():  # raw-data layout
            left_dir, right_dir = left_dir / "data", right_dir / "data"
        if left_dir.is_dir() and right_dir.is_dir():
            lefts, rights = _images_in(left_dir), _images_in(right_dir)
            _check_counts(lefts, rights, left_dir, right_dir)
            return [PairRef(_safe_id(prefix + stem), lefts[stem], rights[stem], meta=dict(meta)) for stem in lefts]
    left, right = _first_existing(folder / "left.png"), _first_existing(folder / "right.png")
    if left is not None and right is not None:
        return [PairRef(_safe_id(prefix.rstrip("-") or folder.name), left, right, meta=dict(meta))]
    return []


def _discover_kitti_unlabelled(root: Path, split: str, **_: Any) -> list[PairRef]:
    """Every KITTI-style pair under ``root`` (any depth); GT files are never read, even if present."""
    folders = [root, *sorted(p for p in root.rglob("*") if p.is_dir())]
    refs: list[PairRef] = []
    for folder in folders:
        if folder.name in ("data", *(name for pair in _UNLABELLED_FOLDERS for name in pair)):
            continue  # view folders are read through their parent
        refs.extend(_unlabelled_pairs(folder, root))
    return refs



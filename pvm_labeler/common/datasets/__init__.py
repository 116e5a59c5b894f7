"""Dataset readers shared by the labeler and the trainer/evaluator (numpy only, never torch).

Each reader discovers (left, right, GT) files in the dataset's OWN official layout and returns :class:`PairRef`
records (paths only, cheap); :func:`load_pair` decodes one into a :class:`StereoSample` with float32 GT maps where
NaN = unknown.

Supported layouts (``root`` is the folder you pass as ``--root``):

- ``kitti15``: ``root/<split>/image_2``, ``image_3``; GT ``disp_occ_0`` and/or ``disp_noc_0`` (uint16 PNG / 256).
- ``kitti12``: ``root/<split>/colored_0``, ``colored_1``; GT ``disp_occ`` and/or ``disp_noc``.
- ``middlebury``: every folder under ``root`` holding a known pair: MiddEval3 (``im0.png``, ``im1.png``,
  ``disp0GT.pfm`` inf = unknown, ``disp1GT.pfm``, ``mask0nocc.png``, ``calib.txt`` ndisp), 2003 (``im2.png``,
  ``im6.png``, ``disp2.png``/``disp6.png`` value / 4), 2001 (``im2``/``im6`` with ``disp2.pgm``/``disp6.pgm`` value / 8;
  tsukuba ``im3``/``im4`` with ``disp3.pgm`` value / 16), 2005 / 2006 (``view1.png``, ``view5.png``, ``disp1.png``,
  ``disp5.png``, beside the views or, for ``<scene>/Illum<i>/Exp<e>/`` views, in ``<scene>/``; value / 1, 2 or 3 for
  FullSize, HalfSize, ThirdSize: see ``readers.middlebury_2005_scale``). 0 = unknown in the integer formats.
- ``eth3d``: ETH3D two-view: ``two_view_training/<scene>/im0.png``, ``im1.png``, ``calib.txt``; GT
  ``two_view_training_gt/<scene>/disp0GT.pfm`` (inf = unknown), ``mask0nocc.png`` (255 = non-occluded); see
  :mod:`.eth3d`.
- ``sceneflow``: FlyingThings3D / Driving / Monkaa: ``<base>/frames_<pass>/<rel>/left/<n>.png`` (or
  ``RGB_<pass>``), ``right/``; GT ``<base>/disparity/<rel>/{left,right}/<n>.pfm``; optional
  ``<base>/occlusion/<rel>/left/<n>.png`` (True = occluded) gives the non-occluded GT.
- ``folder``: any two folders or glob patterns of left/right images (``left=``, ``right=``, optional ``gt=``;
  defaults ``root/left``, ``root/right``, ``root/gt``), paired by file stem (by the folders a glob's wildcards matched
  and the stem when a glob finds two images of one stem: sequences in folders of their own); an image without a
  partner of its name is an error, and only when no stem is shared and the counts match are they paired by sorted
  order (a warning).
- ``kitti_unlabelled``: every folder under ``root`` holding a KITTI-style pair of image folders
  (``image_2``/``image_3``, ``image_02``/``image_03``, or their ``data/`` sub-folders) or a ``left.png``/``right.png``
  pair; frame ids are the relative path joined with ``-``. Never any GT: this is self-supervised training data.
- ``sample``: no files needed: scikit-image's Middlebury 2014 motorcycle pair (GT invalid = +inf -> NaN) plus
  deterministic synthetic layered scenes with exact left, non-occluded and right GT.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pvm_labeler.common import io
from pvm_labeler.common.datasets.eth3d import _discover_eth3d
from pvm_labeler.common.datasets.readers import (
    _discover_folder,
    _discover_kitti12,
    _discover_kitti15,
    _discover_kitti_unlabelled,
    _discover_middlebury,
    _discover_sceneflow,
    read_middlebury_calib,
)
from pvm_labeler.common.datasets.refs import (
    DATASETS,
    DEFAULT_MAX_DISP,
    IMAGE_SUFFIXES,
    SPLITS,
    PairRef,
    StereoSample,
    _require_dir,
    safe_stem,
)
from pvm_labeler.common.datasets.synthetic import SYNTHETIC_SCENES, _discover_sample, make_layered_scene
from pvm_labeler.common.errors import ConfigError, InputError
from pvm_labeler.common.metrics import gt_problems

__all__ = ["DATASETS", "DEFAULT_MAX_DISP", "IMAGE_SUFFIXES", "SPLITS", "SYNTHETIC_SCENES", "PairRef", "StereoSample",
           "check_pair_sizes", "discover", "load_pair", "make_layered_scene", "read_middlebury_calib", "safe_stem"]



# ------------------------------------------------------------------------------------------------- public API
#: The readers that look at ``split`` (the others ignore it, so their messages do not name it).
_SPLIT_AWARE: tuple[str, ...] = ("kitti15", "kitti12", "eth3d", "sceneflow")
_DISCOVER: dict[str, Callable[..., list[PairRef]]] = {
    "kitti15": _discover_kitti15,
    "kitti12": _discover_kitti12,
    "middlebury": _discover_middlebury,
    "eth3d": _discover_eth3d,
    "sceneflow": _discover_sceneflow,
    "folder": _discover_folder,
    "kitti_unlabelled": _discover_kitti_unlabelled,
    "sample": _discover_sample,
}


def discover(name: str, root: Path | str | None, split: str = "training", **kwargs: Any) -> list[PairRef]:
    """List the pairs of a dataset in its official layout, sorted by frame id.

    Args:
        name: one of :data:`DATASETS`.
        root: dataset folder (see the module docstring per dataset); ignored by ``sample``, optional for ``folder``
            when ``left``/``right`` are absolute.
        split: ``training`` or ``testing`` (KITTI split folder; Scene Flow TRAIN/TEST; ETH3D two_view_training /
            two_view_test; ignored by middlebury).
        **kwargs: per-dataset options: ``folder``: ``left``, ``right``, ``gt``, ``gt_scale``; ``sceneflow``:
            ``pass_`` ("clean"/"final"); ``sample``: ``synthetic``, ``motorcycle`` (bools: which pairs to include).

    Returns:
        PairRefs sorted by frame id (ids unique).

    Raises:
        ConfigError: unknown name or split, missing root (usage errors: exit 2 in the CLIs).
        InputError: no pairs found, left/right count mismatch, duplicate ids.
    """
    if name not in _DISCOVER:
        raise ConfigError(f"unknown dataset '{name}'; expected one of {', '.join(DATASETS)}")
    if split not in SPLITS:
        raise ConfigError(f"unknown split '{split}'; expected one of {', '.join(SPLITS)}")
    if name not in ("sample", "folder"):
        if root is None:
            raise ConfigError(f"dataset '{name}' needs --root (the folder holding its official layout)")
        root = Path(root)
        _require_dir(root, f"{name} root")
    elif root is not None:
        root = Path(root)
        if name == "folder":
            _require_dir(root, "folder root")
    refs = _DISCOVER[name](root, split, **kwargs)
    if not refs:
        in_split = f" (split '{split}')" if name in _SPLIT_AWARE else ""
        raise InputError(f"no stereo pairs found for dataset '{name}' under {root}{in_split}")
    refs.sort(key=lambda r: r.frame_id)
    ids = [r.frame_id for r in refs]
    dupes = sorted({i for i in ids if ids.count(i) > 1})
    if dupes:
        raise InputError(f"dataset '{name}' under {root}: duplicate frame ids {dupes[:5]}")
    return refs


def check_pair_sizes(ref: PairRef) -> tuple[int, int]:
    """Pre-flight check from file headers only: left/right/GT files exist, are readable and have equal sizes.

    Returns:
        (H, W) of the pair.

    Raises:
        InputError: naming the files whose sizes differ or that are missing/unreadable.
    """
    if ref.meta.get("synthetic"):
        height, width, _ = ref.meta["synthetic"]
        return int(height), int(width)
    left_hw = io.image_size(ref.left)
    right_hw = io.image_size(ref.right)
    if left_hw != right_hw:
        raise InputError(
            f"left/right sizes differ: {left_hw} vs {right_hw} (H, W) for pair {ref.frame_id}: {ref.left}, {ref.right}"
        )
    for role in ("gt", "gt_noc", "gt_right"):
        path = getattr(ref, role)
        if path is not None and path.suffix != ".npz":
            hw = io.image_size(path)
            if hw != left_hw:
                raise InputError(f"{role} size {hw} differs from image size {left_hw} (H, W) for pair "
                                 f"{ref.frame_id}: {path}")
    return left_hw


def gt_divisor(meta: dict[str, Any]) -> float | None:
    """An integer PNG GT's divisor (disparity = value / divisor) from a pair's metadata; None for float GT."""
    return {"kitti": io.KITTI_SCALE, "scaled": meta.get("gt_scale")}.get(meta.get("gt_format", ""))


def first_gt_problems(refs: list[PairRef]) -> list[str]:
    """The GT check (:func:`pvm_labeler.common.metrics.gt_problems`) of the first pair that has a GT file, as
    "<frame> (<file>): <problem>" lines ([] when none has GT or it looks plausible): a wrong --gt-scale, byte order
    or sign is the same for every file of a dataset, so one pair tells.

    Raises:
        InputError: that pair cannot be read (as the job itself would report it).
    """
    ref = next((r for r in refs if r.gt is not None and not r.meta.get("synthetic")), None)  # a scene's GT is exact
    if ref is None:
        return []
    gt = _read_gt(ref.gt, ref.meta)
    return [f"{ref.frame_id} ({ref.gt}): {problem}" for problem in gt_problems(gt, gt_divisor(ref.meta))]


def _read_gt(path: Path, meta: dict[str, Any]) -> np.ndarray:
    fmt = meta.get("gt_format")
    if fmt == "kitti":
        return io.read_kitti_disp(path)
    if fmt == "scaled":
        raw = io.read_grey_raw(path)
        return io.decode_scaled_disparity(raw, float(meta["gt_scale"]))
    if fmt in ("pfm", "npy"):
        disp = io.read_pfm(path) if fmt == "pfm" else np.load(path).astype(np.float32)
        if disp.ndim != 2:
            raise InputError(f"{path}: expected a single-channel disparity map, got shape {disp.shape}")
        return np.where(np.isfinite(disp), disp, np.nan).astype(np.float32)  # Middlebury: inf = unknown
    if fmt == "skimage_npz":
        with np.load(path) as npz:
            disp = npz["arr_0"].astype(np.float32)
        return np.where(np.isfinite(disp), disp, np.nan).astype(np.float32)  # +inf = invalid despite the docs
    raise InputError(f"{path}: unknown GT format {fmt!r} in pair metadata")


def _load_synthetic(ref: PairRef) -> StereoSample:
    height, width, seed = ref.meta["synthetic"]
    scene = make_layered_scene(int(height), int(width), int(seed))
    return StereoSample(
        frame_id=ref.frame_id,
        left=scene["left"],
        right=scene["right"],
        gt=scene["gt"],
        gt_noc=scene["gt_noc"],
        gt_right=scene["gt_right"],
        sources={"synthetic": f"make_layered_scene({height}, {width}, {seed})"},
        max_disp=DEFAULT_MAX_DISP["sample"],
    )


def load_pair(ref: PairRef) -> StereoSample:
    """Decode one pair: RGB uint8 images and float32 GT maps (NaN = unknown).

    Raises:
        InputError: a file is missing/corrupt, or left/right/GT sizes differ (naming the files).
    """
    if ref.meta.get("synthetic"):
        return _load_synthetic(ref)
    left = io.read_image(ref.left)
    right = io.read_image(ref.right)
    if left.shape != right.shape:
        raise InputError(
            f"left/right sizes differ: {left.shape[:2]} vs {right.shape[:2]} (H, W) for pair {ref.frame_id}: "
            f"{ref.left}, {ref.right}"
        )
    sources = {"left": str(ref.left), "right": str(ref.right)}
    maps: dict[str, np.ndarray | None] = {}
    for role in ("gt", "gt_noc", "gt_right"):
        path = getattr(ref, role)
        maps[role] = None if path is None else _read_gt(path, ref.meta)
        if path is not None:
            sources[role] = str(path)
            if maps[role].shape != left.shape[:2]:
                raise InputError(
                    f"{role} shape {maps[role].shape} differs from image shape {left.shape[:2]} for pair "
                    f"{ref.frame_id}: {path}"
                )
    gt, gt_noc = maps["gt"], maps["gt_noc"]
    if gt is not None and gt_noc is None:
        gt_noc = _noc_from_mask(gt, ref, sources, left.shape[:2])
    max_disp = DEFAULT_MAX_DISP.get(ref.meta.get("dataset", ""))
    if "calib" in ref.meta:
        sources["calib"] = ref.meta["calib"]
        ndisp = read_middlebury_calib(Path(ref.meta["calib"])).get("ndisp")
        max_disp = int(ndisp) if ndisp is not None else max_disp
    return StereoSample(ref.frame_id, left, right, gt, gt_noc, maps["gt_right"], sources, max_disp)


def _noc_from_mask(
    gt: np.ndarray, ref: PairRef, sources: dict[str, str], shape: tuple[int, int]
) -> np.ndarray | None:
    """Non-occluded GT from a Middlebury nocc mask (255 = visible) or a Scene Flow occlusion map (True = occl.)."""
    if "noc_mask" in ref.meta:
        path = Path(ref.meta["noc_mask"])
        mask = io.read_grey_raw(path)
        keep = mask == 255
    elif "occlusion" in ref.meta:
        path = Path(ref.meta["occlusion"])
        mask = io.read_grey_raw(path)
        keep = mask == 0
    else:
        return None
    if mask.shape != shape:
        raise InputError(f"occlusion mask shape {mask.shape} differs from image shape {shape}: {path}")
    sources["noc_mask"] = str(path)
    return np.where(keep, gt, np.nan).astype(np.float32)

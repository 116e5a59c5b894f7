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
  tsukuba ``im3``/``im4`` with ``disp3.pgm`` value / 16). 0 = unknown in the integer formats.
- ``sceneflow``: FlyingThings3D / Driving / Monkaa: ``<base>/frames_<pass>/<rel>/left/<n>.png`` (or
  ``RGB_<pass>``), ``right/``; GT ``<base>/disparity/<rel>/{left,right}/<n>.pfm``; optional
  ``<base>/occlusion/<rel>/left/<n>.png`` (True = occluded) gives the non-occluded GT.
- ``folder``: any two folders or glob patterns of left/right images (``left=``, ``right=``, optional ``gt=``;
  defaults ``root/left``, ``root/right``, ``root/gt``), paired by file stem (or by sorted order when the stems differ
  but the counts match).
- ``kitti_unlabelled``: every folder under ``root`` holding a KITTI-style pair of image folders
  (``image_2``/``image_3``, ``image_02``/``image_03``, or their ``data/`` sub-folders) or a ``left.png``/``right.png``
  pair; frame ids are the relative path joined with ``-``. Never any GT: this is self-supervised training data.
- ``sample``: no files needed: scikit-image's Middlebury 2014 motorcycle pair (GT invalid = +inf -> NaN) plus
  deterministic synthetic layered scenes with exact left, non-occluded and right GT.
"""

from __future__ import annotations

import glob as globlib
import logging
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from pvm_labeler import io
from pvm_labeler.errors import InputError

logger = logging.getLogger(__name__)

DATASETS: tuple[str, ...] = ("kitti15", "kitti12", "middlebury", "sceneflow", "folder", "kitti_unlabelled", "sample")
SPLITS: tuple[str, ...] = ("training", "testing")
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")

#: Search range that comfortably covers a dataset when the user gives no --max-disp (sample GT max is 59.9 px).
DEFAULT_MAX_DISP: dict[str, int] = {"sample": 64}


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
        max_disp: dataset hint for the search range (MiddEval3 calib ndisp), else None.
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
    """stem -> image path for every image file directly inside ``folder``."""
    return {p.stem: p for p in sorted(folder.iterdir()) if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES}


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
    """Make a string usable as an HDF5 group name and file-system friendly ("/" separates HDF5 groups)."""
    text = re.sub(r"[^A-Za-z0-9_.+-]+", "-", text).strip("-.")
    return text or "frame"


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
# (left, right, left GT, right GT, GT scale) per layout; scale None = PFM with inf = unknown.
_MIDDLEBURY_LAYOUTS: tuple[tuple[str, str, str, str, float | None], ...] = (
    ("im0.png", "im1.png", "disp0GT.pfm", "disp1GT.pfm", None),  # MiddEval3 / 2014
    ("im2.png", "im6.png", "disp2.png", "disp6.png", 4.0),  # 2003 (cones, teddy), quarter size
    ("im2.ppm", "im6.ppm", "disp2.pgm", "disp6.pgm", 8.0),  # 2001 (venus, sawtooth, ...)
    ("im2.png", "im6.png", "disp2.pgm", "disp6.pgm", 8.0),
    ("im3.png", "im4.png", "disp3.pgm", "disp4.pgm", 16.0),  # 2001 tsukuba (truedisp scaled by 16)
    ("im3.ppm", "im4.ppm", "disp3.pgm", "disp4.pgm", 16.0),
)


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
            gt=_first_existing(folder / gt_name),
            gt_noc=None,
            gt_right=_first_existing(folder / gt_right_name),
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
def _glob_images(spec: str | Path, root: Path | None, what: str) -> tuple[dict[str, Path], str]:
    spec = Path(spec)
    if root is not None and not spec.is_absolute():
        spec = root / spec
    if spec.is_dir():
        return _images_in(spec), str(spec)
    if any(ch in str(spec) for ch in "*?["):
        files = sorted(Path(p) for p in globlib.glob(str(spec)) if Path(p).suffix.lower() in IMAGE_SUFFIXES)
        return {p.stem: p for p in files}, str(spec)
    raise InputError(f"folder dataset: {what} '{spec}' is neither a directory nor a glob pattern that exists")


def _discover_folder(
    root: Path | None,
    split: str,
    left: str | Path = "left",
    right: str | Path = "right",
    gt: str | Path | None = None,
    gt_scale: float = io.KITTI_SCALE,
    **_: Any,
) -> list[PairRef]:
    lefts, left_spec = _glob_images(left, root, "left")
    rights, right_spec = _glob_images(right, root, "right")
    if set(lefts) == set(rights):
        keys = sorted(lefts)
        pairs = [(k, lefts[k], rights[k]) for k in keys]
    elif len(lefts) == len(rights):
        # Rigs often name the views differently (cam0_0001 / cam1_0001): pair by sorted order, keep the left stem.
        logger.info("folder dataset: left/right stems differ, pairing %d images by sorted order", len(lefts))
        pairs = [(lk, lefts[lk], rights[rk]) for lk, rk in zip(sorted(lefts), sorted(rights), strict=True)]
    else:
        raise InputError(
            f"left/right count mismatch: {len(lefts)} images in {left_spec} vs {len(rights)} in {right_spec}"
        )
    gts: dict[str, Path] = {}
    if gt is None and root is not None and (root / "gt").is_dir():
        gt = "gt"
    if gt is not None:
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


# ------------------------------------------------------------------------------------------------------ sample
#: (height, width, seed) of the synthetic layered scenes in the `sample` dataset. Sizes differ on purpose so
#: consumers cannot assume one shape per shard.
SYNTHETIC_SCENES: tuple[tuple[int, int, int], ...] = ((240, 320, 0), (224, 336, 1), (256, 304, 2))
_SYNTHETIC_MARK = "<synthetic>"


def _discover_sample(
    root: Path | None, split: str, synthetic: bool | str = True, motorcycle: bool | str = True, **_: Any
) -> list[PairRef]:
    import skimage

    data_dir = Path(skimage.__file__).parent / "data"
    refs = []
    if _flag(motorcycle):
        refs.append(
            PairRef(
                frame_id="motorcycle",
                left=data_dir / "motorcycle_left.png",
                right=data_dir / "motorcycle_right.png",
                gt=data_dir / "motorcycle_disp.npz",
                meta={"dataset": "sample", "gt_format": "skimage_npz"},
            )
        )
    if _flag(synthetic):
        for i, (height, width, seed) in enumerate(SYNTHETIC_SCENES):
            fake = Path(_SYNTHETIC_MARK) / f"synthetic-{i:03d}"
            refs.append(
                PairRef(
                    frame_id=f"synthetic-{i:03d}",
                    left=fake / "left",
                    right=fake / "right",
                    gt=fake / "gt",
                    gt_noc=fake / "gt_noc",
                    gt_right=fake / "gt_right",
                    meta={"dataset": "sample", "synthetic": [height, width, seed]},
                )
            )
    return refs


def _flag(value: bool | str) -> bool:
    """Reader options may come from YAML/CLI as strings."""
    return value if isinstance(value, bool) else str(value).lower() not in ("0", "false", "no", "off")


def _smooth_texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Random texture with energy at several scales so every pyramid level has something to match."""
    import cv2

    tex = np.zeros((height, width), np.float32)
    for sigma, weight in ((0.7, 0.5), (2.0, 0.3), (6.0, 0.2)):
        noise = rng.standard_normal((height, width)).astype(np.float32)
        blurred = cv2.GaussianBlur(noise, (0, 0), sigma)
        tex += weight * blurred / (blurred.std() + 1e-6)
    rgb = np.stack([tex, np.roll(tex, 3, axis=1), np.roll(tex, 5, axis=0)], axis=2)
    return np.clip(128 + 40 * rgb, 0, 255).astype(np.float32)


def make_layered_scene(height: int, width: int, seed: int) -> dict[str, np.ndarray]:
    """Render a deterministic synthetic stereo pair with exact GT for both views.

    The scene is a slanted "road" background whose disparity grows linearly with the row (d = 8 + 24 * y / H, so
    each row is a constant sub-pixel shift, rendered with linear interpolation) and two fronto-parallel
    rectangles at integer disparities 30 and 44. Views are composed back to front, so occlusions are physical:
    a left pixel is non-occluded iff the same layer is front-most at x - d in the right view.

    Returns:
        dict with ``left``, ``right`` (H, W, 3) uint8 and ``gt``, ``gt_noc``, ``gt_right`` (H, W) float32,
        NaN = unknown (left pixels whose match falls outside the right image are in ``gt`` but not ``gt_noc``).
    """
    rng = np.random.default_rng([20240613, seed])
    pad = 64  # texture margin so shifted layers never sample outside their texture
    ys = np.arange(height, dtype=np.float32)
    xs = np.arange(width, dtype=np.float32)
    layers = []  # (texture (H, W + pad, 3), disparity (H,) per row, mask function in left coords)
    bg_disp = 8.0 + 24.0 * ys / height
    layers.append((_smooth_texture(rng, height, width + pad), bg_disp, np.ones((height, width + pad), bool)))
    for disp in (30.0, 44.0):
        h0 = int(rng.integers(height // 8, height // 2))
        w0 = int(rng.integers(width // 8, width // 2))
        box_h, box_w = int(rng.integers(height // 5, height // 3)), int(rng.integers(width // 6, width // 4))
        mask = np.zeros((height, width + pad), bool)
        mask[h0 : h0 + box_h, w0 : w0 + box_w] = True
        layers.append((_smooth_texture(rng, height, width + pad), np.full(height, disp, np.float32), mask))

    def render(sign: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # Left view (sign 0): layer pixel u sits at x = u. Right view (sign -1): at x = u - d, i.e. reads u = x + d.
        image = np.zeros((height, width, 3), np.float32)
        disp = np.full((height, width), np.nan, np.float32)
        owner = np.full((height, width), -1, np.int32)
        for index, (tex, row_disp, mask) in enumerate(layers):
            u = xs[None, :] - sign * row_disp[:, None]  # (H, W) source column in layer coordinates
            u0 = np.floor(u).astype(np.int64)
            frac = (u - u0)[..., None]
            u0c, u1c = np.clip(u0, 0, width + pad - 1), np.clip(u0 + 1, 0, width + pad - 1)
            rows = np.arange(height)[:, None]
            value = (1 - frac) * tex[rows, u0c] + frac * tex[rows, u1c]
            inside = mask[rows, u0c] & mask[rows, u1c]
            image[inside] = value[inside]
            disp[inside] = np.broadcast_to(row_disp[:, None], (height, width))[inside]
            owner[inside] = index
        return np.clip(np.round(image), 0, 255).astype(np.uint8), disp, owner

    left, gt, owner_l = render(0.0)
    right, gt_right, owner_r = render(-1.0)
    # Non-occluded: the matching right pixel x - d exists and shows the same layer.
    xr = np.round(xs[None, :] - gt).astype(np.int64)
    inside = (xr >= 0) & (xr < width)
    rows = np.broadcast_to(np.arange(height)[:, None], (height, width))
    same = np.zeros_like(inside)
    same[inside] = owner_r[rows[inside], xr[inside]] == owner_l[inside]
    gt_noc = np.where(same, gt, np.nan).astype(np.float32)
    # A right pixel whose match x + d leaves the left image has no left counterpart: unknown.
    xl = xs[None, :] + gt_right
    gt_right = np.where(xl <= width - 1, gt_right, np.nan).astype(np.float32)
    return {"left": left, "right": right, "gt": gt, "gt_noc": gt_noc, "gt_right": gt_right}


# ------------------------------------------------------------------------------------------------- public API
_DISCOVER: dict[str, Callable[..., list[PairRef]]] = {
    "kitti15": _discover_kitti15,
    "kitti12": _discover_kitti12,
    "middlebury": _discover_middlebury,
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
        split: ``training`` or ``testing`` (KITTI split folder; Scene Flow TRAIN/TEST; ignored by middlebury).
        **kwargs: per-dataset options: ``folder``: ``left``, ``right``, ``gt``, ``gt_scale``; ``sceneflow``:
            ``pass_`` ("clean"/"final"); ``sample``: ``synthetic``, ``motorcycle`` (bools: which pairs to include).

    Returns:
        PairRefs sorted by frame id (ids unique).

    Raises:
        InputError: unknown name/split, missing root, no pairs found, left/right count mismatch, duplicate ids.
    """
    if name not in _DISCOVER:
        raise InputError(f"unknown dataset '{name}'; expected one of {', '.join(DATASETS)}")
    if split not in SPLITS:
        raise InputError(f"unknown split '{split}'; expected one of {', '.join(SPLITS)}")
    if name not in ("sample", "folder"):
        if root is None:
            raise InputError(f"dataset '{name}' needs --root (the folder holding its official layout)")
        root = Path(root)
        _require_dir(root, f"{name} root")
    elif root is not None:
        root = Path(root)
        if name == "folder":
            _require_dir(root, "folder root")
    refs = _DISCOVER[name](root, split, **kwargs)
    if not refs:
        raise InputError(f"no stereo pairs found for dataset '{name}' under {root} (split '{split}')")
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

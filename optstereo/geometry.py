"""Depth and point clouds from disparity and a rectified rig's calibration (numpy only).

Z = fx * baseline / (d + doffs); X = (u - cx) Z / fx; Y = (v - cy) Z / fy, in metres, camera frame of the left view
(x right, y down, z forward). ``doffs`` is the difference of the two cameras' principal points (cx_right - cx_left),
0 for KITTI, non-zero for Middlebury.

Calibration files (:func:`read_calibration` detects the kind):
- KITTI ``calib_cam_to_cam.txt`` (raw/stereo 2015): ``P_rect_02`` / ``P_rect_03`` give fx, fy, cx, cy and the
  baseline (P_rect_02[0, 3] - P_rect_03[0, 3]) / fx (image_2 is the left camera, image_3 the right);
- Middlebury ``calib.txt``: ``cam0``, ``cam1`` matrices, ``doffs``, ``baseline`` in millimetres;
- YAML: ``fx``, ``cx``, ``cy``, ``baseline`` (metres), optional ``fy`` (= fx) and ``doffs`` (= 0).

The image size a file records (KITTI ``S_rect_02``, Middlebury ``width`` / ``height``, YAML ``width`` / ``height``)
must be the pair's (:meth:`Calibration.check_fits`): a resized pair with the original calibration gave depths off by
the ratio, silently.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import yaml

from pvm_labeler.common.atomic import atomic_write_bytes
from pvm_labeler.common.datasets import read_middlebury_calib
from pvm_labeler.common.errors import InputError
from pvm_labeler.common.io import write_image

logger = logging.getLogger(__name__)

DEPTH_PNG_SCALE = 1000.0  # 16-bit depth PNG in millimetres (0 = invalid), as most RGB-D tools (KITTI's
#: depth benchmark stores metres x 256 instead)
DEPTH_PNG_MAX = 65535  # its largest value: 65.535 m


@dataclass(frozen=True)
class Calibration:
    """A rectified stereo rig: focal lengths and principal point (px), baseline (m), principal-point offset (px)."""

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float
    doffs: float = 0.0
    size: tuple[int, int] | None = None  # (H, W) of the images it describes, where the file says (None: unknown)
    source: str = dataclasses.field(default="", compare=False)  # the file it was read from

    def check_fits(self, height: int, width: int) -> None:
        """InputError when the calibration describes images of another size than (``height``, ``width``) (its
        recorded size, else a principal point outside the image): the depth would be off by the size ratio."""
        if self.size is not None and self.size != (height, width):
            raise InputError(f"{self.source or 'the calibration'} describes {self.size[1]}x{self.size[0]} images and "
                             f"the pair is {width}x{height}: its depth would be off by the ratio; give the "
                             "calibration of the images as they are (a resized pair: scale fx, fy, cx, cy alike)")
        if not (0 <= self.cx <= width and 0 <= self.cy <= height):
            raise InputError(f"{self.source or 'the calibration'}: principal point ({self.cx:g}, {self.cy:g}) lies "
                             f"outside the {width}x{height} pair: it describes images of another size")
        if abs(self.cx - width / 2) > width / 4 or abs(self.cy - height / 2) > height / 4:
            logger.warning("%s: principal point (%g, %g) lies far from the centre of the %dx%d pair: a calibration "
                           "of larger images? (its depths would be off by the size ratio; give width and height to "
                           "have it checked)", self.source or "the calibration", self.cx, self.cy, width, height)


def _numbers(text: str) -> list[float]:
    return [float(x) for x in re.findall(r"[-+]?\d*\.?\d+(?:[eE][-+]?\d+)?", text)]


def _read_kitti(lines: dict[str, str], path: Path, left: str = "02", right: str = "03") -> Calibration:
    try:
        p_left = np.array(_numbers(lines[f"P_rect_{left}"]), dtype=np.float64).reshape(3, 4)
        p_right = np.array(_numbers(lines[f"P_rect_{right}"]), dtype=np.float64).reshape(3, 4)
    except (KeyError, ValueError) as exc:
        raise InputError(f"{path}: KITTI calibration needs P_rect_{left} and P_rect_{right} (3x4 each): {exc}") from exc
    fx = p_left[0, 0]
    size = _numbers(lines.get(f"S_rect_{left}", ""))
    return Calibration(fx=fx, fy=p_left[1, 1], cx=p_left[0, 2], cy=p_left[1, 2],
                       baseline=(p_left[0, 3] - p_right[0, 3]) / fx, doffs=p_right[0, 2] - p_left[0, 2],
                       size=(round(size[1]), round(size[0])) if len(size) == 2 else None)


def _read_middlebury(lines: dict[str, str], path: Path) -> Calibration:
    try:
        cam0 = np.array(_numbers(lines["cam0"]), dtype=np.float64).reshape(3, 3)
        baseline_mm = float(lines["baseline"])
        doffs = float(lines.get("doffs", "0"))
    except (KeyError, ValueError) as exc:
        raise InputError(f"{path}: Middlebury calibration needs cam0=[...], baseline= and doffs=: {exc}") from exc
    size = None
    if lines.get("width", "").isdigit() and lines.get("height", "").isdigit():
        size = (int(lines["height"]), int(lines["width"]))
    return Calibration(fx=cam0[0, 0], fy=cam0[1, 1], cx=cam0[0, 2], cy=cam0[1, 2], baseline=baseline_mm / 1000.0,
                       doffs=doffs, size=size)


def _read_yaml(path: Path) -> Calibration:
    text = path.read_text()
    if text.lstrip().startswith("%YAML:1.0"):
        raise InputError(f"{path}: an OpenCV FileStorage file; write the rectified camera as plain YAML keys: fx, cx, "
                         "cy in px (from P1 or the rectified K), baseline in m (|Tx| / fx of P2), optional fy, width, "
                         "height")
    try:
        doc = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML ({str(exc).splitlines()[0]}, line "
                         f"{getattr(getattr(exc, 'problem_mark', None), 'line', -1) + 1})") from exc
    if not isinstance(doc, dict):
        raise InputError(f"{path}: a YAML calibration is 'key: value' lines (fx: 700), got {type(doc).__name__}")
    missing = [k for k in ("fx", "cx", "cy", "baseline") if k not in doc]
    if missing:
        raise InputError(f"{path}: YAML calibration lacks {missing} (fx, cx, cy in px, baseline in m)")

    def number(key: str, kind: type = float, default: float | None = None) -> float:
        value = doc.get(key, default)
        try:
            return kind(value)
        except (TypeError, ValueError):
            raise InputError(f"{path}: {key} must be a number, got {value!r}") from None

    size = (number("height", int), number("width", int)) if "width" in doc and "height" in doc else None
    return Calibration(fx=number("fx"), fy=number("fy", default=doc["fx"]), cx=number("cx"), cy=number("cy"),
                       baseline=number("baseline"), doffs=number("doffs", default=0.0), size=size)


def _key_values(path: Path) -> dict[str, str]:
    """``key: value`` lines (KITTI) or ``key=value`` lines (Middlebury, via the dataset reader's own parser)."""
    text = path.read_text()
    if "P_rect_02" not in text:
        return read_middlebury_calib(path)
    return {k.strip(): v.strip() for k, sep, v in (line.partition(":") for line in text.splitlines()) if sep}


def read_calibration(path: Path | str) -> Calibration:
    """KITTI calib_cam_to_cam.txt, Middlebury calib.txt or YAML (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"calibration file not found: {path}")
    if path.suffix.lower() in (".yaml", ".yml"):
        calib = _read_yaml(path)
    else:
        lines = _key_values(path)
        if "P_rect_02" in lines:
            calib = _read_kitti(lines, path)
        elif "cam0" in lines:
            calib = _read_middlebury(lines, path)
        else:
            raise InputError(f"{path}: not a KITTI calib_cam_to_cam.txt (P_rect_02) or Middlebury calib.txt (cam0); "
                             "a YAML calibration (fx, cx, cy, baseline) is read from a file named .yaml or .yml")
    if calib.fx <= 0 or calib.baseline <= 0:
        raise InputError(f"{path}: focal length and baseline must be > 0, got fx={calib.fx}, baseline={calib.baseline}")
    return dataclasses.replace(calib, source=str(path))


def disparity_to_depth(disp: npt.ArrayLike, calib: Calibration, max_depth: float = np.inf) -> npt.NDArray[np.float32]:
    """(H, W) disparity (px) -> (H, W) float32 depth (m); NaN where d + doffs <= 0, d is not finite or Z > max_depth."""
    d = np.asarray(disp, dtype=np.float64) + calib.doffs
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = calib.fx * calib.baseline / d
    bad = ~np.isfinite(depth) | (d <= 0) | (depth > max_depth)
    return np.where(bad, np.nan, depth).astype(np.float32)


def depth_to_points(
    depth: npt.NDArray[np.floating], calib: Calibration, image: npt.NDArray[np.uint8] | None = None
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint8] | None]:
    """Back-project valid depth pixels: ((N, 3) float32 XYZ in m, (N, 3) uint8 colours or None), row-major order."""
    v, u = np.nonzero(np.isfinite(depth))
    z = depth[v, u].astype(np.float64)
    xyz = np.stack([(u - calib.cx) * z / calib.fx, (v - calib.cy) * z / calib.fy, z], axis=1).astype(np.float32)
    colours = None if image is None else np.ascontiguousarray(image[v, u, :3], dtype=np.uint8)
    return xyz, colours


def write_depth_png(path: Path | str, depth: npt.NDArray[np.floating]) -> None:
    """16-bit PNG in millimetres, 0 = invalid: no depth, or one beyond the format's 65.535 m (such pixels were
    written as 65.535 m, a plausible-looking wall; their count is logged); depth-pfm / depth-npy keep them."""
    mm = np.round(np.nan_to_num(np.asarray(depth, np.float64), nan=0.0) * DEPTH_PNG_SCALE)
    far = mm > DEPTH_PNG_MAX
    if far.any():
        logger.warning("%s: %d pixels (%.1f %%) lie beyond the 16-bit PNG's %.3f m and are written as 0 (invalid); "
                       "depth-pfm or depth-npy keep them", path, far.sum(), 100 * far.mean(),
                       DEPTH_PNG_MAX / DEPTH_PNG_SCALE)
    write_image(Path(path), np.where(far, 0, np.clip(mm, 0, DEPTH_PNG_MAX)).astype(np.uint16))


def write_ply(path: Path | str, xyz: npt.NDArray[np.float32], colours: npt.NDArray[np.uint8] | None = None) -> None:
    """Binary little-endian PLY with float x, y, z (m) and, when given, uchar red, green, blue; written atomically."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colours is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    data = np.empty(len(xyz), dtype=fields)
    data["x"], data["y"], data["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if colours is not None:
        data["red"], data["green"], data["blue"] = colours[:, 0], colours[:, 1], colours[:, 2]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(xyz)}",
              *(f"property {'float' if t == '<f4' else 'uchar'} {name}" for name, t in fields), "end_header"]
    atomic_write_bytes(Path(path), ("\n".join(header) + "\n").encode("ascii") + data.tobytes())


def read_ply(path: Path | str) -> np.ndarray:
    """Read a PLY written by :func:`write_ply` (structured array with x, y, z[, red, green, blue])."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    props = [line.split() for line in raw[:end].decode("ascii").splitlines() if line.startswith("property")]
    dtype = [(name, "<f4" if kind == "float" else "u1") for _, kind, name in props]
    return np.frombuffer(raw[end:], dtype=dtype)

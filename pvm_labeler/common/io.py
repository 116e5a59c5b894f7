"""Field-standard image and disparity file I/O with clear errors (PNG/PGM/PPM via OpenCV, PFM, KITTI uint16 PNG).

Every reader raises :class:`~pvm_labeler.common.errors.InputError` naming the file when it is missing, unreadable,
corrupt or truncated. Images always come out as (H, W, 3) uint8 RGB; conversions (grey -> 3 channels, 16-bit ->
8-bit, RGBA -> RGB) are logged at INFO level with the file name so nothing is converted silently.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from pvm_labeler.common.atomic import atomic_path, atomic_write_bytes
from pvm_labeler.common.errors import InputError

logger = logging.getLogger(__name__)

#: KITTI stores disparity as uint16 PNG with this scale; value 0 means "no GT".
KITTI_SCALE = 256.0


def _read_bytes(path: Path) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"file not found: {path}")
    try:
        return np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc}") from exc


def _decode(path: Path) -> np.ndarray:
    """Decode any OpenCV-readable image at its native depth and channel count (BGR order)."""
    buf = _read_bytes(path)
    if buf.size == 0:
        raise InputError(f"empty image file: {path}")
    # imdecode returns None for corrupt and truncated files (libpng reports "input buffer is incomplete").
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"corrupt or truncated image (cannot decode): {path}")
    return img


#: A 16-bit image whose values all lie below this holds data of 12 bits or fewer (see :func:`read_image`).
LOW_BIT_DEPTH = 4096


def read_image(path: Path | str) -> npt.NDArray[np.uint8]:
    """Read an image as RGB uint8, converting common variants.

    Conversions (each logged with the file name): grey -> replicated to 3 channels; 16-bit -> scaled to 8 bit
    (value / 257, i.e. full range to full range); RGBA -> alpha dropped (FlyingThings3D ships RGBA PNGs with
    alpha == 255). Anything else (float images, 2-channel images) is rejected.

    Args:
        path: image file (PNG, PGM, PPM, JPEG, ...).

    Returns:
        (H, W, 3) uint8 RGB, C-contiguous.

    Raises:
        InputError: file missing, corrupt/truncated, or of an unsupported depth/channel count.
    """
    path = Path(path)
    img = _decode(path)
    if img.dtype == np.uint16:
        logger.info("%s: 16-bit image scaled to 8 bit (value / 257)", path)
        if 0 < (top := int(img.max())) < LOW_BIT_DEPTH:  # 10- or 12-bit sensor data stored in 16 bits
            logger.warning("%s: a 16-bit image whose values stop at %d (10- or 12-bit data?) becomes nearly black "
                           "at value / 257 (max %d of 255), and matching suffers; convert the images to 8 bit at "
                           "their own depth first", path, top, (top + 128) // 257)
        img = ((img.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise InputError(f"{path}: unsupported image dtype {img.dtype}, expected 8- or 16-bit integer")
    if img.ndim == 2:
        logger.info("%s: grey image replicated to 3 channels", path)
        return np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))
    channels = img.shape[2]
    if channels == 1:
        logger.info("%s: grey image replicated to 3 channels", path)
        return np.ascontiguousarray(np.repeat(img, 3, axis=2))
    if channels == 4:
        logger.info("%s: RGBA image, alpha channel dropped", path)
        return np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGRA2RGB))
    if channels == 3:
        return np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
    raise InputError(f"{path}: unsupported channel count {channels}, expected 1, 3 or 4")


def read_grey_raw(path: Path | str) -> np.ndarray:
    """Read a single-channel image at its native depth (uint8 or uint16), e.g. a disparity PNG/PGM or a mask.

    Returns:
        (H, W) uint8 or uint16.
    """
    path = Path(path)
    img = _decode(path)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        else:
            raise InputError(f"{path}: expected a single-channel image, got {img.shape[2]} channels")
    return img


def write_image(path: Path | str, image: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB or (H, W) uint8/uint16 image (PNG etc., by suffix), atomically."""
    path = Path(path)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise InputError(f"cannot encode image for {path} (shape {image.shape}, dtype {image.dtype})")
    atomic_write_bytes(path, buf.tobytes())


# ----------------------------------------------------------------------------------------------------------- PFM
_PFM_HEADER = re.compile(rb"^(Pf|PF)\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s", re.DOTALL)


def read_pfm(path: Path | str) -> npt.NDArray[np.float32]:
    """Read a Portable Float Map (Middlebury, Scene Flow disparity).

    PFM stores rows bottom-to-top; a negative scale means little-endian. inf values are kept (Middlebury uses inf
    for "unknown"); callers decide what they mean.

    Returns:
        (H, W) float32 for ``Pf`` or (H, W, 3) float32 for ``PF``, top row first, native byte order.
    """
    path = Path(path)
    buf = _read_bytes(path).tobytes()
    match = _PFM_HEADER.match(buf)
    if match is None:
        raise InputError(f"{path}: not a PFM file (header {buf[:20]!r}, expected 'Pf'/'PF' W H scale)")
    kind, width, height, scale = match.group(1), int(match.group(2)), int(match.group(3)), float(match.group(4))
    channels = 3 if kind == b"PF" else 1
    count = width * height * channels
    dtype = np.dtype("<f4" if scale < 0 else ">f4")
    start = match.end()
    if len(buf) - start < count * 4:
        raise InputError(f"{path}: truncated PFM: {len(buf) - start} data bytes, expected {count * 4}")
    data = np.frombuffer(buf, dtype=dtype, count=count, offset=start).astype(np.float32)
    shape = (height, width, 3) if channels == 3 else (height, width)
    return np.ascontiguousarray(np.flipud(data.reshape(shape)))


def write_npy(path: Path | str, array: np.ndarray) -> None:
    """Write ``array`` as a NumPy ``.npy`` file, atomically (a full disk leaves no truncated file under ``path``)."""
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:  # an error names the file (atomic_path)
        np.save(fh, array)


def write_pfm(path: Path | str, array: np.ndarray) -> None:
    """Write (H, W) or (H, W, 3) float32 as little-endian PFM (bottom-to-top rows), atomically."""
    array = np.asarray(array, dtype=np.float32)
    if array.ndim == 2:
        kind = b"Pf"
    elif array.ndim == 3 and array.shape[2] == 3:
        kind = b"PF"
    else:
        raise InputError(f"write_pfm {path}: expected (H, W) or (H, W, 3), got shape {array.shape}")
    height, width = array.shape[:2]
    header = kind + b"\n" + f"{width} {height}\n-1.0\n".encode()
    body = np.ascontiguousarray(np.flipud(array)).astype("<f4").tobytes()
    atomic_write_bytes(Path(path), header + body)


# ------------------------------------------------------------------------------------------------- KITTI disparity
def decode_scaled_disparity(raw: np.ndarray, scale: float) -> npt.NDArray[np.float32]:
    """Integer disparity image -> float32 disparity (value / scale), 0 -> NaN (the common "no GT" code)."""
    disp = raw.astype(np.float32) / np.float32(scale)
    disp[raw == 0] = np.nan
    return disp


def read_kitti_disp(path: Path | str) -> npt.NDArray[np.float32]:
    """Read a KITTI uint16 disparity PNG: disparity = value / 256, 0 = no GT.

    Returns:
        (H, W) float32, NaN where there is no ground truth.
    """
    path = Path(path)
    raw = read_grey_raw(path)
    if raw.dtype != np.uint16:
        raise InputError(f"{path}: KITTI disparity must be a 16-bit PNG, got {raw.dtype}")
    return decode_scaled_disparity(raw, KITTI_SCALE)


def write_kitti_disp(path: Path | str, disp: np.ndarray) -> None:
    """Write (H, W) float disparity as KITTI uint16 PNG (round(d * 256), NaN/inf/<=0 -> 0 = invalid)."""
    disp = np.asarray(disp, dtype=np.float64)
    if disp.ndim != 2:
        raise InputError(f"write_kitti_disp {path}: expected (H, W), got shape {disp.shape}")
    valid = np.isfinite(disp) & (disp > 0)
    raw = np.zeros(disp.shape, dtype=np.uint16)
    # Clip to the uint16 range; a valid disparity below 1/256 would round to the "invalid" code, so keep it at 1.
    raw[valid] = np.clip(np.round(disp[valid] * KITTI_SCALE), 1, 65535).astype(np.uint16)
    write_image(Path(path), raw)


# ------------------------------------------------------------------------------------------------ cheap headers
def image_size(path: Path | str) -> tuple[int, int]:
    """(H, W) of an image or PFM file from its header only (no pixel decoding), for cheap pre-flight checks.

    Raises:
        InputError: the file is missing or its header is not a readable image/PFM header.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"file not found: {path}")
    if path.suffix.lower() == ".pfm":
        with path.open("rb") as fh:
            match = _PFM_HEADER.match(fh.read(64))
        if match is None:
            raise InputError(f"{path}: not a PFM file")
        return int(match.group(3)), int(match.group(2))
    if path.suffix.lower() == ".npy":
        arr = np.load(path, mmap_mode="r")
        return int(arr.shape[0]), int(arr.shape[1])
    # Pillow reads only the header on open(); decoding is deferred, so this costs ~0.1 ms per file.
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            width, height = img.size
    except (UnidentifiedImageError, OSError) as exc:
        raise InputError(f"corrupt or unreadable image header: {path} ({exc})") from exc
    return int(height), int(width)


#: The disparity file formats every command writes, by suffix: KITTI 16-bit PNG, PFM, NumPy (float32 both).
DISPARITY_SUFFIXES = ("png", "pfm", "npy")


def write_disparity_file(path: Path | str, disp: np.ndarray) -> None:
    """Write an (H, W) disparity in the format its suffix names (``DISPARITY_SUFFIXES``), atomically. Pixels
    without a value (NaN) follow each format's convention: 0 in a KITTI PNG, inf in a PFM (Middlebury's), NaN in
    a ``.npy``."""
    suffix = Path(path).suffix.lstrip(".").lower()
    disp = np.asarray(disp, dtype=np.float32)
    if suffix == "png":
        write_kitti_disp(path, disp)
    elif suffix == "pfm":
        write_pfm(path, np.where(np.isfinite(disp), disp, np.float32(np.inf)))
    elif suffix == "npy":
        write_npy(path, disp)
    else:
        raise InputError(f"{path}: a disparity file is one of {', '.join(DISPARITY_SUFFIXES)}")


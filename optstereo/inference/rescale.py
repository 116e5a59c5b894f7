"""Resizing a stereo pair and its disparities by one factor: inference at another input scale (``--scale``) and
the training's spatial scale augmentation (``--scale-range``); pure helpers, which ``optstereo.inference.engine.run``
calls.

A disparity is a horizontal distance in pixels of the image it was measured on, so resizing a pair's width from W
to w multiplies its disparities by w / W. Rows stay aligned under a resize of both views, so the pair stays
rectified.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

__all__ = ["ADAPTIVE_MIN_GAIN", "ADAPTIVE_PERCENTILE", "adaptive_factor", "budget_factor", "disparity_to_size",
           "rescaled_pair", "scaled_size", "shrink_factor", "sparse_to_size"]

#: The percentile of a first pass's disparity that :func:`adaptive_factor` compares with the model's reference: the
#: top of the pair's disparity range, robust to a few wild pixels.
ADAPTIVE_PERCENTILE = 95.0
#: Below this enlargement :func:`adaptive_factor` answers 1: a second pass would cost a whole network run for a change
#: of a fraction of a 1/8-grid cell (a KITTI frame a few pixels smaller than the reference frame).
ADAPTIVE_MIN_GAIN = 1.1


def scaled_size(shape: tuple[int, ...], scale: float) -> tuple[int, int]:
    """(h, w) = (round(H * scale), round(W * scale)) of an (H, W, ...) shape, at least 8 x 8 (the network's 1/8)."""
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    return max(8, round(shape[0] * scale)), max(8, round(shape[1] * scale))


def rescaled_pair(left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8],
                  scale: float) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]:
    """Both (H, W, 3) uint8 images resized to (round(H * scale), round(W * scale)) (at least 8x8): area averaging
    when shrinking (no aliasing), bilinear when enlarging. Rows stay aligned, so the pair stays rectified."""
    h, w = scaled_size(left.shape, scale)
    size = (w, h)  # cv2 wants (width, height)
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return cv2.resize(left, size, interpolation=interp), cv2.resize(right, size, interpolation=interp)


def disparity_to_size(disp: npt.NDArray[np.float32], shape: tuple[int, int]) -> npt.NDArray[np.float32]:
    """(h, w) disparity of a rescaled pair -> (H, W) = ``shape``: bilinear, and values times W / w, because a
    disparity is a horizontal distance in pixels of the image it was measured on."""
    h_out, w_out = shape
    resized = cv2.resize(disp, (w_out, h_out), interpolation=cv2.INTER_LINEAR)
    return (resized * (w_out / disp.shape[1])).astype(np.float32)


def sparse_to_size(label: npt.NDArray[np.float32], shape: tuple[int, int],
                   scale_values: bool = True) -> npt.NDArray[np.float32]:
    """(H, W) sparse map (NaN = none) -> ``shape`` by nearest neighbour, so no label is blended with a hole or a
    neighbour across an edge; with ``scale_values`` (disparities) times w / W, else as is (confidences).

    Nearest by pixel centres (INTER_NEAREST_EXACT), the convention of the images' area/bilinear resize; plain
    INTER_NEAREST takes floor(x * W / w) and would shift the labels up to half a pixel right and down of their images.
    """
    h_out, w_out = shape
    resized = cv2.resize(label, (w_out, h_out), interpolation=cv2.INTER_NEAREST_EXACT)
    return (resized * (w_out / label.shape[1]) if scale_values else resized).astype(np.float32)


def adaptive_factor(disp: npt.NDArray[np.float32], ref_disp: float, ref_pixels: int, prior: float = 1.0) -> float:
    """How much more than its first pass to enlarge a pair so that its disparities reach the model's reference.

    ``disp`` is the (H, W) disparity of the first pass, at the input's size and in its pixels; ``ref_disp`` is the
    same statistic (the ADAPTIVE_PERCENTILE-th percentile) of the pairs the model learned on, measured the same way;
    ``ref_pixels`` their pixel count. The factor is min(ref_disp / p, sqrt(ref_pixels / (H * W))) with p the pair's
    percentile: large enough that the pair's disparities span as many grid cells as the training pairs' did, and
    never more pixels than a training pair. It is 1 (no second pass) when that is below ADAPTIVE_MIN_GAIN, so a pair
    with disparities as large as the references' is never shrunk and one of their size never enlarged.

    ``prior``: the first pass already ran the pair enlarged by this much (:func:`budget_factor`), so its disparities
    and pixels count ``prior`` and ``prior ** 2`` times over: the factor is counted from there.
    """
    if ref_disp <= 0 or ref_pixels <= 0:
        raise ValueError(f"adaptive scale needs positive references, got ref_disp {ref_disp}, ref_pixels {ref_pixels}")
    finite = disp[np.isfinite(disp)]
    top = float(np.percentile(finite, ADAPTIVE_PERCENTILE)) if finite.size else 0.0
    by_disp = ref_disp / (top * prior) if top > 0 else math.inf
    by_pixels = math.sqrt(ref_pixels / (disp.shape[0] * disp.shape[1])) / prior
    factor = min(by_disp, by_pixels)
    return factor if factor >= ADAPTIVE_MIN_GAIN else 1.0


def shrink_factor(shape: tuple[int, ...], ref_pixels: int) -> float:
    """How much to shrink an (H, W, ...) pair with more pixels than ``ref_pixels`` so that it has that many:
    sqrt(ref_pixels / (H W)); 1 when that is above 1 / ADAPTIVE_MIN_GAIN, as :func:`budget_factor` leaves a pair near
    the reference size alone (a KITTI frame of 376x1241 is 866 pixels over a 375x1242 one). Registration T12."""
    if ref_pixels <= 0:
        raise ValueError(f"the pixel cap needs a positive reference, got ref_pixels {ref_pixels}")
    factor = math.sqrt(ref_pixels / (shape[0] * shape[1]))
    return factor if factor * ADAPTIVE_MIN_GAIN <= 1.0 else 1.0


def budget_factor(shape: tuple[int, ...], ref_pixels: int, cap: float, scale: float = 1.0) -> float:
    """How much to enlarge an (H, W, ...) pair, already resized by ``scale``, before its first pass so that it has
    ``ref_pixels`` pixels (a training-size pair's, so no more time per pass than one): min(cap, sqrt(ref_pixels /
    (H W)) / scale); 1 when that is below ADAPTIVE_MIN_GAIN (a pair near the reference size is never resampled for
    a fraction of a grid cell) or ``cap`` <= 1 (off). Never below 1: a larger pair is not shrunk."""
    if ref_pixels <= 0:
        raise ValueError(f"the pixel budget needs a positive reference, got ref_pixels {ref_pixels}")
    factor = min(cap, math.sqrt(ref_pixels / (shape[0] * shape[1])) / scale)
    return factor if factor >= ADAPTIVE_MIN_GAIN else 1.0

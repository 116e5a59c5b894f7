"""Resizing a stereo pair and its disparities by one factor: inference at another input scale (``--scale``) and
the training's spatial scale augmentation (``--scale-range``).

A disparity is a horizontal distance in pixels of the image it was measured on, so resizing a pair's width from W
to w multiplies its disparities by w / W. Rows stay aligned under a resize of both views, so the pair stays
rectified.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

__all__ = ["disparity_to_size", "rescaled_pair", "scaled_size", "sparse_to_size"]


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

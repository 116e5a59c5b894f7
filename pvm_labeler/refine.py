"""Edge-aware refinement of a dense disparity map: the colour-weighted median filter of stereo post-processing.

A network that predicts at 1/8 resolution and upsamples blurs depth edges over a few pixels: values between the two
surfaces, wrong for both. The weighted median replaces each pixel near a depth discontinuity by the median of its
window's disparities, weighted by how alike the pixels' colours are, so the edge snaps to the colour edge. Pixels
whose window spans at most ``min_range`` px of disparity are left as they are (there the median would change them by
less than that, and skipping them keeps the filter fast). NumPy/OpenCV/numba only: the labeler never imports torch.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from pvm_labeler.kernels.wmedian import weighted_median_kernel


@dataclass(frozen=True)
class MedianParams:
    """Weighted-median settings: window radius (px), colour sigma (8-bit RGB units), disparity range (px) below which
    a window is left alone."""

    # chosen without GT on the unlabelled training pairs' PVM labels (pipelines/studies/refine_study.py choose;
    # RESULTS.md)
    radius: int = 5
    sigma: float = 51.0
    min_range: float = 1.0

    def __post_init__(self) -> None:
        if self.radius < 1:
            raise ValueError(f"weighted median radius must be >= 1, got {self.radius}")
        if not self.sigma > 0:
            raise ValueError(f"weighted median sigma must be > 0, got {self.sigma}")
        if self.min_range < 0:
            raise ValueError(f"weighted median min_range must be >= 0, got {self.min_range}")


def edge_pixels(disp: npt.NDArray[np.float32], radius: int, min_range: float) -> npt.NDArray[np.bool_]:
    """(H, W) bool: pixels whose (2r+1)^2 window spans more than ``min_range`` px of finite disparity, or NaN pixels."""
    finite = np.isfinite(disp)
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    high = cv2.dilate(np.where(finite, disp, -np.inf).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    low = cv2.erode(np.where(finite, disp, np.inf).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    with np.errstate(invalid="ignore"):
        return ~finite | (high - low > min_range)


def weighted_median(disp: npt.NDArray[np.float32], image: npt.NDArray[np.uint8],
                    params: MedianParams = MedianParams()) -> npt.NDArray[np.float32]:
    """Colour-weighted median of ``disp`` guided by ``image`` (see the module docstring).

    Args:
        disp: (H, W) float32 disparity, NaN = none (filled where a window has finite values).
        image: (H, W, 3) uint8 RGB of the same view.
        params: window radius, colour sigma, range threshold.

    Returns:
        (H, W) float32 refined disparity; each output is one of the input values of its window.
    """
    if disp.ndim != 2 or image.shape[:2] != disp.shape or image.ndim != 3:
        raise ValueError(f"weighted_median: disparity {disp.shape} and image {image.shape} do not match")
    disp = np.ascontiguousarray(disp, dtype=np.float32)
    todo = edge_pixels(disp, params.radius, params.min_range)
    out = np.empty_like(disp)
    weighted_median_kernel(disp, np.ascontiguousarray(image, dtype=np.float32), todo, params.radius,
                           np.float32(1.0 / (2.0 * params.sigma**2)), out)
    return out

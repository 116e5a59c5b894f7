"""Semi-Global Matching for both views from one census cost volume (Python orchestration of the numba kernels).

Pipeline per call: census transform of both images -> left cost volume C_l (H, W, D) uint8 -> forward sweep +
backward sweep with fused WTA for the left view; then C_r(x, d) = C_l(x + d, d) and the same two sweeps for the
right view. Disparities are positive for both views: left(x) matches right(x - d), right(x) matches left(x + d).

Reference:
    H. Hirschmueller, "Stereo Processing by Semiglobal Matching and Mutual Information", IEEE TPAMI 30(2), 2008.
    R. Zabih, J. Woodfill, "Non-parametric Local Transforms for Computing Visual Correspondence", ECCV 1994.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from pvm_labeler.config import LabelerConfig
from pvm_labeler.errors import InputError
from pvm_labeler.kernels.aggregate import SENTINEL, aggregate_backward_wta, aggregate_forward
from pvm_labeler.kernels.cost import census_dtype, census_transform, cost_volume, reindex_right

logger = logging.getLogger(__name__)

MAX_CENSUS_WINDOW = 7  # 7 x 7 - 1 = 48 bits fit one uint64 code


@dataclass
class SGMResult:
    """SGM output of one view.

    Attributes:
        disp: (H, W) float32 sub-pixel disparity (positive), NaN = no valid match (best d has no partner pixel).
        conf: (H, W) float32 normalized inverse cost c = clip(1 - S_min / (n_paths * C_max), 0, 1), where S_min is
            the minimal aggregated cost of the pixel and C_max = census_window**2 - 1 the largest census cost
            (so n_paths * C_max is what a pixel pays if it matches nothing along any path). Higher = better
            match; 0 at NaN pixels.
        uniqueness: (H, W) float32 1 - S_min / S_second, S_second = min aggregated cost over |d - d_best| > 1;
            0 at NaN pixels. Used by the "SGM + LR + uniqueness-ratio filter" baseline.
    """

    disp: npt.NDArray[np.float32]
    conf: npt.NDArray[np.float32]
    uniqueness: npt.NDArray[np.float32]


def _check_image(name: str, img: np.ndarray) -> np.ndarray:
    if not isinstance(img, np.ndarray):
        raise InputError(f"{name} must be a numpy array, got {type(img).__name__}")
    if img.ndim != 2:
        raise InputError(f"{name} must be a (H, W) grey image, got ndim={img.ndim} shape={img.shape}")
    if img.dtype != np.uint8:
        raise InputError(f"{name} must be uint8, got dtype {img.dtype}")
    return np.ascontiguousarray(img)


def check_inputs(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, max_disp: int | None) -> tuple[
        np.ndarray, np.ndarray, int]:
    """Validate the images and the search range; return C-contiguous images and the number of disparities D.

    Raises:
        InputError: wrong type/ndim/dtype, different shapes, image narrower than D or smaller than the census
            window, census window > 7, or penalties too large for the uint16 aggregation.
    """
    left = _check_image("left", left)
    right = _check_image("right", right)
    if left.shape != right.shape:
        raise InputError(f"left/right sizes differ: {left.shape} vs {right.shape}")
    n_disp = cfg.max_disp if max_disp is None else max_disp
    if int(n_disp) != n_disp or n_disp < 2:
        raise InputError(f"max_disp must be an integer >= 2, got {n_disp}")
    n_disp = int(n_disp)
    height, width = left.shape
    if width < n_disp:
        raise InputError(f"image width {width} must be >= max_disp {n_disp}")
    window = cfg.census_window
    if window > MAX_CENSUS_WINDOW or window < 3 or window % 2 == 0:
        raise InputError(f"census_window must be odd in [3, {MAX_CENSUS_WINDOW}], got {window}")
    if height < window or width < window:
        raise InputError(f"image size {(height, width)} is smaller than the census window {window}x{window}")
    c_max = window * window - 1
    if c_max + cfg.p2 >= SENTINEL or cfg.p1 > cfg.p2 or cfg.p1 < 0:
        raise InputError(f"SGM penalties need 0 <= p1 <= p2 and C_max + p2 < {SENTINEL}, got p1={cfg.p1}, "
                         f"p2={cfg.p2}, C_max={c_max}")
    # 8 paths of at most C_max + P2 each must fit the uint16 S volume.
    if cfg.paths * (c_max + cfg.p2) > 0xFFFF:
        raise InputError(f"{cfg.paths} paths x (C_max={c_max} + p2={cfg.p2}) overflows the uint16 cost sum (65535)")
    return left, right, n_disp


def _aggregate_view(cost: np.ndarray, grey: np.ndarray, cfg: LabelerConfig, s_buffer: np.ndarray,
                    right_view: bool, c_max: int) -> SGMResult:
    """Forward + backward sweeps with fused WTA on one view's cost volume (s_buffer is scratch, reused)."""
    height, width, n_disp = cost.shape
    diag = cfg.paths == 8
    aggregate_forward(cost, grey, cfg.p1, cfg.p2, cfg.p2_adaptive, diag, s_buffer)
    disp = np.empty((height, width), dtype=np.float32)
    conf = np.empty((height, width), dtype=np.float32)
    uniq = np.empty((height, width), dtype=np.float32)
    key_shift = max(1, int(n_disp - 1).bit_length())
    aggregate_backward_wta(cost, grey, cfg.p1, cfg.p2, cfg.p2_adaptive, diag, s_buffer, False, right_view,
                           float(cfg.paths * c_max), key_shift, disp, conf, uniq)
    return SGMResult(disp=disp, conf=conf, uniqueness=uniq)


def sgm_pair(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, max_disp: int | None = None,
             right_view: bool = True) -> tuple[SGMResult, SGMResult | None]:
    """SGM disparity of the left view, and of the right view from the same census cost volume.

    Args:
        left, right: (H, W) uint8 grey rectified images (copied if not C-contiguous).
        cfg: labeler config (census_window, paths, p1, p2, p2_adaptive, max_disp).
        max_disp: overrides cfg.max_disp; disparities searched are [0, max_disp).
        right_view: also compute the right view (cost re-indexed as C_r(x, d) = C_l(x + d, d)).

    Returns:
        (left result, right result or None). Peak memory ~ H * W * D * (1 + 2 + 1) bytes with the right view
        (C_l uint8, one reused uint16 S scratch, C_r uint8).
    """
    left, right, n_disp = check_inputs(left, right, cfg, max_disp)
    height, width = left.shape
    window = cfg.census_window
    c_max = window * window - 1
    census_l = np.empty((height, width), dtype=census_dtype(window))
    census_r = np.empty((height, width), dtype=census_dtype(window))
    census_transform(left, window, census_l)
    census_transform(right, window, census_r)
    cost_l = np.empty((height, width, n_disp), dtype=np.uint8)
    cost_volume(census_l, census_r, c_max, cost_l)
    s_buffer = np.empty((height, width, n_disp), dtype=np.uint16)
    res_left = _aggregate_view(cost_l, left, cfg, s_buffer, False, c_max)
    if not right_view:
        return res_left, None
    cost_r = np.empty_like(cost_l)
    reindex_right(cost_l, c_max, cost_r)
    del cost_l
    res_right = _aggregate_view(cost_r, right, cfg, s_buffer, True, c_max)
    return res_left, res_right

"""Semi-Global Matching for both views from one census cost volume (Python orchestration of the numba kernels).

Pipeline per call: census transform of both images -> left cost volume C_l (H, W, D) uint8 -> forward sweep +
backward sweep with fused WTA for the left view; then C_r(x, d) = C_l(x + d, d) and the same two sweeps for the
right view. Disparities are positive for both views: left(x) matches right(x - d), right(x) matches left(x + d).

Reference:
    H. Hirschmueller, "Stereo Processing by Semiglobal Matching and Mutual Information", IEEE TPAMI 30(2), 2008.
    R. Zabih, J. Woodfill, "Non-parametric Local Transforms for Computing Visual Correspondence", ECCV 1994.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from pvm_labeler.common.errors import InputError
from pvm_labeler.config import CENSUS_WINDOWS, LabelerConfig, census_max_cost, penalty_problem
from pvm_labeler.kernels._lanes import disparity_padding, path_lanes
from pvm_labeler.kernels.aggregate import aggregate_backward_wta, aggregate_forward
from pvm_labeler.kernels.cost import census_dtype, census_transform, cost_volume, cost_volume_right
from pvm_labeler.parallel import run_two

logger = logging.getLogger(__name__)

# Reused scratch for the cost and S volumes. Freshly allocated 100-MB arrays cost page faults and zeroing in the
# kernel; measured on a KITTI frame: 46-730 ms of system time per call (noisy, depends on memory pressure) on top
# of ~500 ms of compute. Two per process, grown on demand: the main one (S, C_l, C_r) and the helper's (the right
# view's own S while it runs beside the left view, see parallel.run_two).


class _Arena:
    """A reused flat uint8 scratch buffer; a concurrent caller that finds it busy gets a fresh array instead."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.buffer: np.ndarray | None = None

    @contextlib.contextmanager
    def take(self, nbytes: int) -> Iterator[np.ndarray]:
        """The first ``nbytes`` of the arena (grown if needed) for the body's duration."""
        if not self.lock.acquire(blocking=False):
            yield np.empty(nbytes, dtype=np.uint8)
            return
        try:
            if self.buffer is None or self.buffer.size < nbytes:
                self.buffer = None  # drop the old one before allocating the larger one
                self.buffer = np.empty(nbytes, dtype=np.uint8)
            yield self.buffer[:nbytes]
        finally:
            self.lock.release()

    def release(self) -> None:
        with self.lock:
            self.buffer = None


_MAIN_ARENA = _Arena()
_HELPER_ARENA = _Arena()


def release_workspace() -> None:
    """Free the cached SGM scratch arenas (they hold up to ~H * W * D * 6 bytes of the largest frame seen)."""
    _MAIN_ARENA.release()
    _HELPER_ARENA.release()


def _views(arena: np.ndarray, shape: tuple[int, int, int], right_view: bool) -> tuple[np.ndarray, ...]:
    """Split a flat uint8 arena into S (uint16), C_l and C_r (uint8) volumes of ``shape`` (C_r None if unused)."""
    n = shape[0] * shape[1] * shape[2]
    s_buffer = arena[: 2 * n].view(np.uint16).reshape(shape)
    cost_l = arena[2 * n : 3 * n].reshape(shape)
    cost_r = arena[3 * n : 4 * n].reshape(shape) if right_view else None
    return s_buffer, cost_l, cost_r


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
            0 at NaN pixels. Used by the "SGM + LR + uniqueness-ratio filter" baseline; None unless requested
            (``sgm_pair(..., uniqueness=True)``: one more pass over every pixel's S).
    """

    disp: npt.NDArray[np.float32]
    conf: npt.NDArray[np.float32]
    uniqueness: npt.NDArray[np.float32] | None


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
            window; and, for a config that skipped ``LabelerConfig.validate``, a census window or penalties beyond
            the kernels' limits (the same checks, from the constants in ``config.py``).
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
    if window not in CENSUS_WINDOWS:
        raise InputError(f"census_window must be one of {CENSUS_WINDOWS}, got {window}")
    if height < window or width < window:
        raise InputError(f"image size {(height, width)} is smaller than the census window {window}x{window}")
    problem = penalty_problem(window, cfg.paths, cfg.p1, cfg.p2)  # LabelerConfig.validate's check, for raw configs
    if problem:
        raise InputError(problem)
    return left, right, n_disp


def _aggregate_view(cost: np.ndarray, grey: np.ndarray, cfg: LabelerConfig, s_buffer: np.ndarray,
                    right_view: bool, c_max: int, n_disp: int, lanes: tuple[type, int],
                    uniqueness: bool = False) -> SGMResult:
    """Forward + backward sweeps with fused WTA on one view's cost volume (s_buffer is scratch, reused).

    cost: (H, W, D_pad) uint8 with the disparities [0, n_disp) searched and padding beyond; lanes: the path-cost
    type and sentinel (both from ``_lanes.py``).
    """
    height, width, _ = cost.shape
    diag = cfg.paths == 8
    aggregate_forward(cost, grey, cfg.p1, cfg.p2, cfg.p2_adaptive, diag, s_buffer, *lanes)
    disp = np.empty((height, width), dtype=np.float32)
    conf = np.empty((height, width), dtype=np.float32)
    uniq = np.empty((height, width), dtype=np.float32)
    aggregate_backward_wta(cost, grey, cfg.p1, cfg.p2, cfg.p2_adaptive, diag, s_buffer, right_view,
                           float(cfg.paths * c_max), n_disp, disp, conf, uniq, *lanes, uniqueness)
    return SGMResult(disp=disp, conf=conf, uniqueness=uniq if uniqueness else None)


def sgm_pair(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, max_disp: int | None = None,
             right_view: bool = True, uniqueness: bool = False) -> tuple[SGMResult, SGMResult | None]:
    """SGM disparity of the left view, and of the right view from the same census cost volume.

    Args:
        left, right: (H, W) uint8 grey rectified images (copied if not C-contiguous).
        cfg: labeler config (census_window, paths, p1, p2, p2_adaptive, max_disp).
        max_disp: overrides cfg.max_disp; disparities searched are [0, max_disp).
        right_view: also compute the right view (cost re-indexed as C_r(x, d) = C_l(x + d, d)).
        uniqueness: also compute the left view's uniqueness ratio (``SGMResult.uniqueness``; off by default, it
            costs one more pass over S per pixel and only the uniqueness-filter baseline uses it).

    Returns:
        (left result, right result or None); their arrays are freshly allocated. Scratch ~ H * W * D * 4 bytes with
        the right view (S uint16, C_l and C_r uint8) lives in a per-process arena reused by the next call (see
        :func:`release_workspace`); another H * W * D * 2 bytes (the right view's S) when the two views run side by
        side, which they do when the thread budget is >= 2 cores (:func:`pvm_labeler.parallel.run_two`). The results
        do not depend on it.
    """
    left, right, n_disp = check_inputs(left, right, cfg, max_disp)
    height, width = left.shape
    window = cfg.census_window
    c_max = census_max_cost(window)
    census_l = np.empty((height, width), dtype=census_dtype(window))
    census_r = np.empty((height, width), dtype=census_dtype(window))
    census_transform(left, window, census_l)
    census_transform(right, window, census_r)
    # D rounded up to the vector width when the bounds allow it: no scalar remainder loops (exact, see _lanes.py)
    n_padded, pad_cost = disparity_padding(c_max, cfg.p1, cfg.p2, n_disp)
    lanes = path_lanes(c_max, cfg.p1, cfg.p2)  # uint8 path costs when they fit (2x the SIMD lanes of uint16)
    shape = (height, width, n_padded)
    n_cells = height * width * n_padded
    with _MAIN_ARENA.take(n_cells * (4 if right_view else 3)) as arena:
        s_buffer, cost_l, cost_r = _views(arena, shape, right_view)
        cost_volume(census_l, census_r, c_max, cost_l, n_disp, pad_cost)
        if not right_view:
            return _aggregate_view(cost_l, left, cfg, s_buffer, False, c_max, n_disp, lanes, uniqueness), None
        cost_volume_right(census_l, census_r, c_max, cost_r, n_disp, pad_cost)  # = C_l(x + d, d), re-indexed

        def right_sweeps(concurrent: bool) -> SGMResult:
            if not concurrent:  # after the left view: its S scratch is free again
                return _aggregate_view(cost_r, right, cfg, s_buffer, True, c_max, n_disp, lanes)
            with _HELPER_ARENA.take(2 * n_cells) as scratch:
                s_right = scratch.view(np.uint16).reshape(shape)
                return _aggregate_view(cost_r, right, cfg, s_right, True, c_max, n_disp, lanes)

        # The two views' sweeps are independent: beside each other when a second core is free (parallel.run_two).
        return run_two(lambda: _aggregate_view(cost_l, left, cfg, s_buffer, False, c_max, n_disp, lanes, uniqueness),
                       right_sweeps)

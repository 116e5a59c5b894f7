"""Numba reference kernels that only the tests use, built from the production kernels' own building blocks.

The production sweep never stores the full aggregated cost S (the WTA consumes one pixel's S at a time), and the
matcher never runs a WTA over a whole volume; these wrappers expose both so that tests can compare them with the
pure-NumPy references of ``naive.py``. No on-disk cache: they inline production functions, whose edits a cache
keyed by this file alone would miss.
"""

import numpy as np
from numba import njit, prange

from pvm_labeler.kernels._flags import FASTMATH
from pvm_labeler.kernels.aggregate import _buffers, _pixel, p2_table
from pvm_labeler.kernels.wta import disparity_ramp, select_disparity


@njit(fastmath=FASTMATH)
def backward_sum(cost, grey, p1, p2, adaptive, diag, s, lane_dtype, sentinel):
    """The backward sweep of ``aggregate_backward_wta`` (same ``_pixel``), writing S = forward + backward into ``s``.

    Args:
        cost: (H, W, D) uint8; grey: (H, W) uint8; p1, p2, adaptive, diag, lane_dtype, sentinel: as in
            ``aggregate_forward``.
        s: (H, W, D) uint16, the forward sums in, the full S out (updated in place).
    """
    height, width, n_disp = cost.shape
    even, odd, horiz, mins, _ = _buffers(width, n_disp, lane_dtype, sentinel)
    table = p2_table(p1, p2, adaptive)
    for y in range(height - 1, -1, -1):
        prev, cur = (odd, even) if y & 1 == 0 else (even, odd)
        hmin = np.uint16(0)
        for x in range(width - 1, -1, -1):
            hmin, _ = _pixel(cost, grey, y, x, -1, p1, table, diag, prev, cur, horiz, mins, hmin, s, y, x, s, y, x)


@njit(fastmath=FASTMATH, parallel=True)
def wta_volume(cost_sum, right_view, s_max, disp, conf, uniq):
    """The production per-pixel WTA (``wta.select_disparity``) over a whole aggregated volume.

    Args:
        cost_sum: (H, W, D) uint16 aggregated cost S.
        right_view: False: d is valid iff x - d >= 0; True: valid iff x + d < W.
        s_max: see ``select_disparity``.
        disp, conf, uniq: (H, W) float32 outputs, written in place.
    """
    height, width, n_disp = cost_sum.shape
    ramp = disparity_ramp(n_disp)
    for y in prange(height):
        for x in range(width):
            n_valid = width - x if right_view else x + 1
            disp[y, x], conf[y, x], uniq[y, x] = select_disparity(cost_sum, y, x, n_disp, n_valid, s_max, -1,
                                                                  ramp, True)

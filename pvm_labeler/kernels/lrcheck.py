"""Left-right disparity consistency check (LRDCC) as a numba kernel.

Kernel module: @njit functions over NumPy arrays only. The Python wrapper is ``pvm_labeler.multiscale.lr_check``.
"""

import numpy as np
from numba import njit, prange

from pvm_labeler.kernels._flags import FASTMATH


@njit(cache=True, fastmath=FASTMATH, parallel=True)
def lr_check_kernel(disp_l, disp_r, threshold, out_l, out_r):
    """Keep each view's disparity only where the other view agrees within ``threshold`` pixels.

    Left pixel x with d = D_l(x) looks up the right view at the ROUNDED column xr = floor(x - d + 0.5) and is kept iff
    0 <= xr < W, D_r(xr) is finite and |d - D_r(xr)| <= threshold. Symmetrically a right pixel x with d = D_r(x) looks
    up xl = floor(x + d + 0.5) in the left view. Rounding (not interpolation) is used because both inputs are
    semi-dense: a bilinear lookup would reject every pixel next to a hole. Both checks read the unfiltered inputs.

    Args:
        disp_l: (H, W) float32 left-view disparity, left(x) matches right(x - d); NaN = none.
        disp_r: (H, W) float32 right-view disparity, right(x) matches left(x + d); NaN = none.
        threshold: maximum absolute disagreement in pixels.
        out_l: (H, W) float32 output, disp_l where consistent, else NaN.
        out_r: (H, W) float32 output, disp_r where consistent, else NaN.
    """
    height, width = disp_l.shape
    nan = np.float32(np.nan)
    for y in prange(height):
        for x in range(width):
            out_l[y, x] = nan
            d = disp_l[y, x]
            if np.isfinite(d):
                xr = np.int64(np.floor(x - d + 0.5))
                if 0 <= xr < width:
                    dr = disp_r[y, xr]
                    if np.isfinite(dr) and abs(d - dr) <= threshold:
                        out_l[y, x] = d
            out_r[y, x] = nan
            d = disp_r[y, x]
            if np.isfinite(d):
                xl = np.int64(np.floor(x + d + 0.5))
                if 0 <= xl < width:
                    dl = disp_l[y, xl]
                    if np.isfinite(dl) and abs(d - dl) <= threshold:
                        out_r[y, x] = d

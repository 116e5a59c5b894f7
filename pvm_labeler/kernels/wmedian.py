"""Colour-weighted median filter of a disparity map as a numba kernel.

Kernel module: @njit functions over NumPy arrays only. The Python wrapper is ``pvm_labeler.refine.weighted_median``.
"""

import numpy as np
from numba import njit, prange

from pvm_labeler.kernels._flags import FASTMATH


@njit(cache=True, fastmath=FASTMATH, parallel=True)
def weighted_median_kernel(disp, guide, todo, radius, inv_two_sigma2, out):
    """Exact weighted median of the disparities in a (2r+1)^2 window, weighted by colour similarity to the centre.

    At each pixel with ``todo`` set, the window's finite disparities d_q get weights
    w_q = exp(-|I_p - I_q|^2 / (2 sigma^2)) (I = guide colour); the output is the smallest d_q whose cumulative
    weight, in order of d, reaches half the total: one of the window's own values, so a blurred depth edge snaps to
    the side whose colour the pixel shares. Pixels without ``todo`` (or whose window holds no finite value) keep
    their input.

    Args:
        disp: (H, W) float32 disparity, NaN = none.
        guide: (H, W, C) float32 guide image (colour units of ``sigma``).
        todo: (H, W) bool, pixels to filter.
        radius: window radius r (window side 2r + 1).
        inv_two_sigma2: 1 / (2 sigma^2) of the colour weight.
        out: (H, W) float32 output.

    Reference:
        Ma, Li, Zhang, Hu: "Constant Time Weighted Median Filtering for Stereo Matching and Beyond", ICCV 2013.
    """
    height, width = disp.shape
    channels = guide.shape[2]
    side = 2 * radius + 1
    for y in prange(height):
        values = np.empty(side * side, np.float32)
        weights = np.empty(side * side, np.float32)
        for x in range(width):
            out[y, x] = disp[y, x]
            if not todo[y, x]:
                continue
            count = 0
            total = np.float32(0.0)
            for yy in range(max(0, y - radius), min(height, y + radius + 1)):
                for xx in range(max(0, x - radius), min(width, x + radius + 1)):
                    d = disp[yy, xx]
                    if not np.isfinite(d):
                        continue
                    dist2 = np.float32(0.0)
                    for c in range(channels):
                        diff = guide[yy, xx, c] - guide[y, x, c]
                        dist2 += diff * diff
                    w = np.float32(np.exp(-dist2 * inv_two_sigma2))
                    # insertion into the sorted prefix: no allocation per pixel (this is the inference hot path),
                    # and a window is nearly sorted along its rows on smooth surfaces
                    i = count
                    while i > 0 and values[i - 1] > d:
                        values[i] = values[i - 1]
                        weights[i] = weights[i - 1]
                        i -= 1
                    values[i] = d
                    weights[i] = w
                    total += w
                    count += 1
            if count == 0:
                continue
            half = total * np.float32(0.5)
            acc = np.float32(0.0)
            for i in range(count):
                acc += weights[i]
                if acc >= half:
                    out[y, x] = values[i]
                    break

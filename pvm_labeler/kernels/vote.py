"""Multi-scale variance voting (PVM, Wang et al., Section III-A) as a numba kernel.

Kernel module: @njit functions over NumPy arrays only (no logging, no exceptions on data values).
The Python wrapper is ``pvm_labeler.multiscale.vote``.
"""

import numpy as np
from numba import njit, prange

try:
    from pvm_labeler.kernels._flags import FASTMATH
except ImportError:  # A1's shared flag module not committed yet; same contract: no nnan/ninf (NaN is a sentinel)
    FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}

# label_mode values (the wrapper maps LabelerConfig.label_mode strings to these).
LABEL_WEIGHTED = 0  # sum_k w_k D^k / sum_k w_k with caller-given weights (finest scale only: w = [1, 0, ...])
LABEL_MEDIAN = 1  # median of D^k over the scales


@njit(cache=True, fastmath=FASTMATH, parallel=True)
def vote_kernel(disp, conf, kappa1, kappa2, label_mode, weights, out_label, out_conf, out_c1, out_c2):
    """Variance voting over K full-resolution scale maps, one pixel at a time.

    A pixel is kept iff every scale is finite there (disparity and c) and V(p) = [C1 >= kappa1] + [C2 >= kappa2] = 0,
    with C1 = std_k D^k(p), C2 = std_k c^k(p) (population std, ddof = 0, two-pass in float64).

    Args:
        disp: (K, H, W) float32 disparities already brought to full resolution (NaN = invalid).
        conf: (K, H, W) float32 normalized inverse cost c in [0, 1] at full resolution (NaN = invalid).
        kappa1: threshold on C1 in full-resolution pixels.
        kappa2: threshold on C2 (unitless).
        label_mode: LABEL_WEIGHTED or LABEL_MEDIAN.
        weights: (K,) float64 non-negative scale weights for LABEL_WEIGHTED (sum > 0).
        out_label: (H, W) float32 output, voted disparity, NaN where rejected.
        out_conf: (H, W) float32 output, mean_k c^k * (1 - C1 / kappa1) * (1 - C2 / kappa2); 0 where rejected.
        out_c1: (H, W) float32 output, C1 (NaN where some scale is invalid).
        out_c2: (H, W) float32 output, C2 (NaN where some scale is invalid).
    """
    n_scales, height, width = disp.shape
    nan = np.float32(np.nan)
    for y in prange(height):
        scratch = np.empty(n_scales, dtype=np.float64)  # per-row buffer for the median
        for x in range(width):
            valid = True
            sum_d = 0.0
            sum_c = 0.0
            for k in range(n_scales):
                d = disp[k, y, x]
                c = conf[k, y, x]
                if not (np.isfinite(d) and np.isfinite(c)):
                    valid = False
                    break
                sum_d += d
                sum_c += c
            if not valid:
                out_label[y, x] = nan
                out_conf[y, x] = 0.0
                out_c1[y, x] = nan
                out_c2[y, x] = nan
                continue
            mean_d = sum_d / n_scales
            mean_c = sum_c / n_scales
            var_d = 0.0
            var_c = 0.0
            for k in range(n_scales):
                dd = disp[k, y, x] - mean_d
                dc = conf[k, y, x] - mean_c
                var_d += dd * dd
                var_c += dc * dc
            c1 = np.sqrt(var_d / n_scales)
            c2 = np.sqrt(var_c / n_scales)
            out_c1[y, x] = c1
            out_c2[y, x] = c2
            if not (c1 < kappa1 and c2 < kappa2):
                out_label[y, x] = nan
                out_conf[y, x] = 0.0
                continue
            out_label[y, x] = _combine(disp, y, x, label_mode, weights, scratch)
            score = mean_c * (1.0 - c1 / kappa1) * (1.0 - c2 / kappa2)
            out_conf[y, x] = min(max(score, 0.0), 1.0)


@njit(cache=True, fastmath=FASTMATH)
def _combine(disp, y, x, label_mode, weights, scratch):
    """Label value of one kept pixel from its K scale disparities (see LABEL_* constants)."""
    n_scales = disp.shape[0]
    if label_mode == LABEL_MEDIAN:
        # Insertion sort: K is small (~6), and this avoids an allocation per pixel.
        for k in range(n_scales):
            v = np.float64(disp[k, y, x])
            j = k - 1
            while j >= 0 and scratch[j] > v:
                scratch[j + 1] = scratch[j]
                j -= 1
            scratch[j + 1] = v
        mid = n_scales // 2
        if n_scales % 2 == 1:
            return scratch[mid]
        return 0.5 * (scratch[mid - 1] + scratch[mid])
    num = 0.0
    den = 0.0
    for k in range(n_scales):
        num += weights[k] * disp[k, y, x]
        den += weights[k]
    return num / den

"""Multi-scale variance voting (PVM, Wang et al., Section III-A) as a numba kernel.

Kernel module: @njit functions over NumPy arrays only (no logging, no exceptions on data values).
The Python wrapper is ``pvm_labeler.multiscale.vote``.
"""

import numpy as np
from numba import njit, prange

from pvm_labeler.kernels._flags import FASTMATH

# label_mode values (the wrapper maps LabelerConfig.label_mode strings to these).
LABEL_WEIGHTED = 0  # sum_k w_k D^k / sum_k w_k with caller-given weights (finest scale only: w = [1, 0, ...])
LABEL_MEDIAN = 1  # median of D^k over the scales


@njit(cache=True, fastmath=FASTMATH, parallel=True)
def vote_kernel(disp, conf, kappa1, kappa2, c2_scale, label_mode, weights, out_label, out_conf, out_c1, out_c2):
    """Variance voting over K full-resolution scale maps.

    A pixel is kept iff every scale is finite there (disparity and c) and V(p) = [C1 >= kappa1] + [C2 >= kappa2] = 0,
    with C1 = std_k D^k(p), C2 = std_k c^k(p) (population std, ddof = 0, two-pass in float64).

    Each row is processed as contiguous loops over x (one pass per scale), which LLVM vectorizes; a NaN or inf at
    any scale makes the float64 sum non-finite, so validity needs no per-element branch.

    Args:
        disp: (K, H, W) float32 disparities already brought to full resolution (NaN = invalid).
        conf: (K, H, W) float32 normalized inverse cost c in [0, 1] at full resolution (NaN = invalid).
        kappa1: threshold on C1 in full-resolution pixels.
        kappa2: threshold on C2 (unitless).
        c2_scale: normaliser of C2 in the soft confidence (kappa2 before the two were decoupled; see out_conf).
        label_mode: LABEL_WEIGHTED or LABEL_MEDIAN.
        weights: (K,) float64 non-negative scale weights for LABEL_WEIGHTED (sum > 0).
        out_label: (H, W) float32 output, voted disparity, NaN where rejected.
        out_conf: (H, W) float32 output, mean_k c^k * (1 - C1 / kappa1) * (1 - C2 / c2_scale), clipped to
            [0, 1]; 0 where rejected.
        out_c1: (H, W) float32 output, C1 (NaN where some scale is invalid).
        out_c2: (H, W) float32 output, C2 (NaN where some scale is invalid).
    """
    n_scales, height, width = disp.shape
    nan = np.float32(np.nan)
    inv_k = 1.0 / n_scales
    wsum = 0.0
    for k in range(n_scales):
        wsum += weights[k]
    for y in prange(height):
        mean_d = np.zeros(width, dtype=np.float64)
        mean_c = np.zeros(width, dtype=np.float64)
        var_d = np.zeros(width, dtype=np.float64)
        var_c = np.zeros(width, dtype=np.float64)
        comb = np.zeros(width, dtype=np.float64)
        scratch = np.empty(n_scales, dtype=np.float64)
        for k in range(n_scales):
            wk = weights[k]
            for x in range(width):
                d = np.float64(disp[k, y, x])
                mean_d[x] += d
                mean_c[x] += conf[k, y, x]
                comb[x] += wk * d
        for x in range(width):
            mean_d[x] *= inv_k
            mean_c[x] *= inv_k
        for k in range(n_scales):
            for x in range(width):
                dd = disp[k, y, x] - mean_d[x]
                dc = conf[k, y, x] - mean_c[x]
                var_d[x] += dd * dd
                var_c[x] += dc * dc
        for x in range(width):
            if not (np.isfinite(mean_d[x]) and np.isfinite(mean_c[x])):
                out_label[y, x] = nan
                out_conf[y, x] = 0.0
                out_c1[y, x] = nan
                out_c2[y, x] = nan
                continue
            c1 = np.sqrt(var_d[x] * inv_k)
            c2 = np.sqrt(var_c[x] * inv_k)
            out_c1[y, x] = c1
            out_c2[y, x] = c2
            if not (c1 < kappa1 and c2 < kappa2):
                out_label[y, x] = nan
                out_conf[y, x] = 0.0
                continue
            if label_mode == LABEL_MEDIAN:
                out_label[y, x] = _median(disp, y, x, scratch)
            else:
                out_label[y, x] = comb[x] / wsum
            score = mean_c[x] * (1.0 - c1 / kappa1) * (1.0 - c2 / c2_scale)
            out_conf[y, x] = min(max(score, 0.0), 1.0)


@njit(cache=True, fastmath=FASTMATH)
def _median(disp, y, x, scratch):
    """Median of disp[:, y, x] (K small, ~6: insertion sort into a per-row scratch, no allocation per pixel)."""
    n_scales = disp.shape[0]
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

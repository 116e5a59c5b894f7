"""Numba winner-takes-all on the aggregated SGM cost: sub-pixel disparity, confidence c and uniqueness.

Definitions (per pixel, S = aggregated cost vector over d in [0, D), uint16):
    d* = argmin_d S(d) (smallest d on ties), S_min = S(d*).
    disparity = d* + (S(d*-1) - S(d*+1)) / (2 (S(d*-1) - 2 S(d*) + S(d*+1))), the vertex of the parabola through
        the three costs; no offset at d* = 0, d* = D - 1 or a flat triple. NaN when d* has no partner pixel, or
        when the minimum is not unique (S(d) == S_min for some |d - d*| > 1: e.g. no texture along the row).
    c = clip(1 - S_min / s_max, 0, 1) with s_max = n_paths * max_cost (the cost of a pixel that matches nothing
        along any path); 0 at NaN pixels.
    uniqueness = 1 - S_min / S_second, S_second = min over |d - d*| > 1 (0 if S_second == 0, no such d or NaN).
"""

import numpy as np
from numba import njit, prange

from pvm_labeler.kernels._flags import FASTMATH


@njit(cache=True, fastmath=FASTMATH, inline="always")
def select_disparity(s, y, x, n_disp, n_valid, s_max, s_min_known):
    """WTA + parabola + c + uniqueness of one pixel (see the module docstring).

    Args:
        s, y, x: the pixel's aggregated costs are s[y, x, :], (D,) uint16 (three entries are overwritten
            temporarily and restored). Indexing the (H, W, D) volume directly instead of taking an s[y, x] view
            per pixel matters: a view per pixel costs reference counting in numba (see aggregate.py).
        n_disp: the disparities searched, [0, n_disp) (<= s.shape[2]: slots beyond are padding, costlier than any
            real S_min; see ``_lanes.disparity_padding``).
        n_valid: disparities d < n_valid have a partner pixel; d* >= n_valid gives NaN.
        s_max: normaliser of c (float).
        s_min_known: min_d S if the caller has it already (the backward sweep tracks it while it writes S, for free),
            else any negative number: it is then computed here (one uint16 min reduction).

    Returns:
        (disparity, c, uniqueness) as float32 scalars.
    """
    if s_min_known >= 0:
        smin = np.uint16(s_min_known)
    else:
        smin = np.uint16(0xFFFF)
        for d in range(n_disp):
            smin = min(smin, s[y, x, d])
    # d* = the first d at the minimum: a short scan (d* is small for most pixels) replaces a full-length argmin.
    # It first skips whole blocks of 16 without a hit (a fixed-length compare LLVM vectorises), then scans one
    # block: 26 -> 23 ms per KITTI frame (D = 192) against a plain scalar scan.
    start = 0
    n_blocks_end = n_disp - n_disp % 16
    while start < n_blocks_end:
        hit = False
        for k in range(16):
            hit |= s[y, x, start + k] == smin
        if hit:
            break
        start += 16
    d_best = 0
    for d in range(start, n_disp):
        if s[y, x, d] == smin:
            d_best = d
            break
    s_min = np.float32(smin)
    if d_best >= n_valid:
        return np.float32(np.nan), np.float32(0.0), np.float32(0.0)
    # Second best outside d* +- 1: overwrite the three slots with the max, take one full-length min (a fixed trip
    # count vectorises without scalar remainders; a masked loop did not vectorise), then restore them.
    lo = max(d_best - 1, 0)
    hi = min(d_best + 2, n_disp)
    saved0 = s[y, x, lo]
    saved1 = s[y, x, lo + 1] if lo + 1 < hi else np.uint16(0)
    saved2 = s[y, x, lo + 2] if lo + 2 < hi else np.uint16(0)
    for d in range(lo, hi):
        s[y, x, d] = np.uint16(0xFFFF)
    second = np.uint16(0xFFFF)
    for d in range(n_disp):
        second = min(second, s[y, x, d])
    s[y, x, lo] = saved0
    if lo + 1 < hi:
        s[y, x, lo + 1] = saved1
    if lo + 2 < hi:
        s[y, x, lo + 2] = saved2
    found = d_best >= 2 or d_best + 2 < n_disp
    if found and np.float32(second) == s_min:
        # an exact tie with a distant disparity: no unique match (e.g. a region without texture along x)
        return np.float32(np.nan), np.float32(0.0), np.float32(0.0)
    uniq = np.float32(0.0)
    if found and second > 0:
        uniq = np.float32(1.0) - s_min / np.float32(second)
    offset = np.float32(0.0)
    if 0 < d_best < n_disp - 1:
        a = np.float32(s[y, x, d_best - 1])
        c = np.float32(s[y, x, d_best + 1])
        denom = a - np.float32(2.0) * s_min + c
        if denom > 0:
            offset = (a - c) / (np.float32(2.0) * denom)
    conf = np.float32(1.0) - s_min / np.float32(s_max)
    conf = min(max(conf, np.float32(0.0)), np.float32(1.0))
    return np.float32(d_best) + offset, conf, uniq


@njit(cache=True, fastmath=FASTMATH, parallel=True)
def wta_volume(cost_sum, right_view, s_max, disp, conf, uniq):
    """Apply :func:`select_disparity` to every pixel of an aggregated volume.

    Args:
        cost_sum: (H, W, D) uint16 aggregated cost S.
        right_view: False: d is valid iff x - d >= 0; True: valid iff x + d < W.
        s_max: see :func:`select_disparity`.
        disp, conf, uniq: (H, W) float32 outputs, written in place.
    """
    height, width, n_disp = cost_sum.shape
    for y in prange(height):
        for x in range(width):
            n_valid = width - x if right_view else x + 1
            disp[y, x], conf[y, x], uniq[y, x] = select_disparity(cost_sum, y, x, n_disp, n_valid, s_max, -1)

"""Numba winner-takes-all on the aggregated SGM cost: sub-pixel disparity, confidence c and uniqueness.

Definitions (per pixel, S = aggregated cost vector over d in [0, D), uint16):
    d* = argmin_d S(d) (smallest d on ties), S_min = S(d*).
    disparity = d* + (S(d*-1) - S(d*+1)) / (2 (S(d*-1) - 2 S(d*) + S(d*+1))), the vertex of the parabola through
        the three costs; no offset at d* = 0, d* = D - 1 or a flat triple. NaN when d* has no partner pixel, or
        when the minimum is not unique (S(d) == S_min for some |d - d*| > 1: e.g. no texture along the row).
    c = clip(1 - S_min / s_max, 0, 1) with s_max = n_paths * max_cost (the cost of a pixel that matches nothing
        along any path); 0 at NaN pixels.
    uniqueness = 1 - S_min / S_second, S_second = min over |d - d*| > 1 (0 if S_second == 0, no such d or NaN);
        computed on request only (``want_uniq``).
"""

import numpy as np
from numba import njit

from pvm_labeler.kernels._flags import FASTMATH


@njit(cache=True, fastmath=FASTMATH, inline="always")
def select_disparity(s, y, x, n_disp, n_valid, s_max, s_min_known, ramp, want_uniq):
    """WTA + parabola + c + uniqueness of one pixel (see the module docstring).

    Args:
        s, y, x: the pixel's aggregated costs are s[y, x, :], (D,) uint16 (read only). Indexing the (H, W, D)
            volume directly instead of taking an s[y, x] view per pixel matters: a view per pixel costs reference
            counting in numba (see aggregate.py).
        n_disp: the disparities searched, [0, n_disp) (<= s.shape[2]: slots beyond are padding, costlier than any
            real S_min; see ``_lanes.disparity_padding``).
        n_valid: disparities d < n_valid have a partner pixel; d* >= n_valid gives NaN.
        s_max: normaliser of c (float).
        s_min_known: min_d S if the caller has it already (the backward sweep tracks it while it writes S, for free),
            else any negative number: it is then computed here (one uint16 min reduction).
        ramp: (D,) uint16 with ramp[d] = d (:func:`disparity_ramp`), D = s.shape[2].
        want_uniq: compute the uniqueness (one more pass over S); else it is returned as 0.

    Returns:
        (disparity, c, uniqueness) as float32 scalars.
    """
    # d*, and the last d at S_min for the tie test, in ONE branch-free pass of uint16 min / max reductions over the
    # whole, vector-aligned length (the padded slots of ``_lanes.disparity_padding`` cost more than every real S).
    # The disparity index comes from the uint16 ``ramp`` (ramp[d] = d), not from the int64 loop counter, so every
    # lane is 16 bits wide. Against the earlier scan for the first d at S_min (it branched on every pixel) plus an
    # always-on second-best pass: backward sweep + WTA of a KITTI left view 47 -> 41 ms, same maps bit for bit.
    n_all = s.shape[2]
    if s_min_known >= 0:
        smin = np.uint16(s_min_known)
    else:
        smin = np.uint16(0xFFFF)
        for d in range(n_all):
            smin = min(smin, s[y, x, d])
    first = np.uint16(0xFFFF)
    last = np.uint16(0)
    for d in range(n_all):
        hit = s[y, x, d] == smin
        first = min(first, ramp[d] if hit else np.uint16(0xFFFF))
        last = max(last, ramp[d] if hit else np.uint16(0))
    d_best = np.int64(first)
    s_min = np.float32(smin)
    # d* has no partner pixel, or S_min recurs at some d >= d* + 2 (d* is the first minimum, so this is "a tie
    # outside d* +- 1"): no unique match, e.g. a region without texture along x.
    if d_best >= n_valid or d_best >= n_disp or np.int64(last) >= d_best + 2:
        return np.float32(np.nan), np.float32(0.0), np.float32(0.0)
    uniq = np.float32(0.0)
    if want_uniq:
        # Second best outside d* +- 1: ramp[d] - lo < band as ONE unsigned compare selects the band to leave out.
        lo = max(d_best - 1, 0)
        lo16 = np.uint16(lo)
        band = np.uint16(min(d_best + 2, n_disp) - lo)
        second = np.uint16(0xFFFF)
        for d in range(n_all):
            v = s[y, x, d]
            second = min(second, np.uint16(0xFFFF) if np.uint16(ramp[d] - lo16) < band else v)
        found = d_best >= 2 or d_best + 2 < n_disp
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


@njit(cache=True, fastmath=FASTMATH)
def disparity_ramp(n_disp):
    """(n_disp,) uint16 [0, 1, ..., n_disp - 1]: the disparity index as a 16-bit vector lane (n_disp <= 65536)."""
    ramp = np.empty(n_disp, dtype=np.uint16)
    for d in range(n_disp):
        ramp[d] = np.uint16(d)
    return ramp

"""Numba SGM path aggregation (Hirschmueller 2008), one sweep per scan-direction family.

For a path direction r: L_r(p, d) = C(p, d) + min(L_r(p-r, d), L_r(p-r, d+-1) + P1, min_k L_r(p-r, k) + P2)
- min_k L_r(p-r, k); a path starts at the image border with L_r = C. S(p, d) = sum_r L_r(p, d).

* :func:`aggregate_forward` runs the paths that arrive from the left or from above (left->right and top, plus
  top-left and top-right with ``diag``) in one top-to-bottom sweep and stores their sum.
* :func:`aggregate_backward_wta` runs the mirrored paths bottom-to-top, adds the stored forward sum and calls the
  winner-takes-all of ``wta.py`` on each finished S vector, so the full S volume is read only once more.

Speed notes: the path arithmetic is uint8 when the penalties allow it, else uint16 (``_lanes.py``), always with
explicit casts (numba would widen to int64; narrow lanes let LLVM pack 32 uint8 / 16 uint16 lanes into an AVX2
vector). The paths of a sweep are updated in ONE loop over d, then their uint16 sum is written in a second short
loop (one fused loop mixing the widths vectorised worse: 106 vs 72 ms for the backward sweep). The volumes and row
buffers are indexed, never sliced per pixel (see :func:`step4`). Only previous-row buffers (W + 2, D + 2) per path
are kept, walked in ascending addresses by both sweeps. The two extra disparity slots hold a sentinel so the
d +- 1 reads need no branch; the two extra columns stay zero (a path entering the image has L = C).
Both sweeps release the GIL (``nogil``): ``sgm.sgm_pair`` may run the right view's sweeps on a helper thread
beside the left view's (``parallel.run_two``). They call no ``prange`` kernel, so they are safe under any numba
threading layer. The wrapper guarantees L_r <= C_max + P2 < sentinel, the lane bounds of ``_lanes.path_lanes`` and
n_paths * (C_max + P2) <= 65535, so nothing wraps.
"""

import numpy as np
from numba import njit

from pvm_labeler.kernels._flags import FASTMATH
from pvm_labeler.kernels._lanes import lane
from pvm_labeler.kernels._prefetch import prefetch
from pvm_labeler.kernels.wta import disparity_ramp, select_disparity

PREFETCH_AHEAD = 4  # pixels; 2-16 measured alike on a KITTI frame (99-100 ms), 0 = no prefetch (142 ms)


@njit(cache=True, fastmath=FASTMATH)
def p2_table(p1, p2, adaptive):
    """(256,) uint16 P2 by grey-level step g = |I(p) - I(p - r)|: P2 // max(1, g) clamped to >= P1 when
    ``adaptive``, else the constant P2. A table because an integer division per path and pixel, even on the
    non-adaptive branch that LLVM evaluated speculatively, cost ~17 ms per sweep on a KITTI frame."""
    table = np.empty(256, dtype=np.uint16)
    for g in range(256):
        table[g] = np.uint16(max(p1, p2 // max(1, g))) if adaptive else np.uint16(p2)
    return table


@njit(cache=True, fastmath=FASTMATH, inline="always")
def penalty2(table, grey, y, x, py, px):
    """P2 for the step (py, px) -> (y, x): table[|I(y, x) - I(py, px)|].

    A neighbour outside the image is clamped into it: there the path starts (its previous L is 0 everywhere), and
    the start value min(0, ..., 0 + P2) = 0 does not depend on P2.
    """
    py = min(max(py, 0), grey.shape[0] - 1)
    px = min(max(px, 0), grey.shape[1] - 1)
    return table[abs(np.int32(grey[y, x]) - np.int32(grey[py, px]))]


# The recurrence is written out per path below on purpose: moving it into an inlined helper function makes
# LLVM give up on vectorizing the d loop (measured: 12x slower). min(L(d - 1), L(d + 1)) + P1 is one add fewer than
# min(L(d - 1) + P1, L(d + 1) + P1) and equal, since nothing wraps (bounds in _lanes.py): forward sweep -3 %.


@njit(cache=True, fastmath=FASTMATH, inline="always")
def step4(cost, y, x, base, by, bx, out, oy, ox, bufs, rows, pms, qs, p1):
    """Four paths of pixel (y, x) in one pass over d, then their sum; returns the minima of the four new L vectors
    and of the written totals.

    Args:
        cost: (H, W, D) uint8, this pixel's costs are cost[y, x].
        base, by, bx / out, oy, ox: out[oy, ox, d] = base[by, bx, d] + sum_k L_k(d) ((., ., D) uint16; may alias).
        bufs: (a0, a1, a2, a3, o0, o1, o2, o3) 2-D (rows, D + 2) buffers, all uint8 or all uint16 (the lane type):
            a_k[rows[k]] holds the previous L_k (sentinels in slots 0 and D + 1), o_k[rows[k + 4]] receives the new
            L_k in slots 1..D.
        pms: the minima of the four previous vectors; qs: P2 of each path (uint16); p1: P1.

    Every array is indexed here, never sliced: taking per-pixel views (cost[y, x], buf[col], ...) made numba
    reference-count each view, ~24 ms of fixed per-pixel overhead per sweep on a KITTI frame.
    """
    n_disp = cost.shape[2]
    a0, a1, a2, a3, o0, o1, o2, o3 = bufs
    r0, r1, r2, r3, w0, w1, w2, w3 = rows
    pm0, pm1, pm2, pm3 = pms
    pen = lane(p1, a0)
    j0 = lane(pm0 + qs[0], a0)
    j1 = lane(pm1 + qs[1], a0)
    j2 = lane(pm2 + qs[2], a0)
    j3 = lane(pm3 + qs[3], a0)
    m0 = lane(pm0, a0)
    m1 = lane(pm1, a0)
    m2 = lane(pm2, a0)
    m3 = lane(pm3, a0)
    n0 = lane(0xFFFF, a0)
    n1 = n0
    n2 = n0
    n3 = n0
    for d in range(n_disp):
        cd = cost[y, x, d]
        v0 = min(min(a0[r0, d + 1], j0), lane(min(a0[r0, d], a0[r0, d + 2]) + pen, a0))
        l0 = lane(cd + lane(v0 - m0, a0), a0)
        v1 = min(min(a1[r1, d + 1], j1), lane(min(a1[r1, d], a1[r1, d + 2]) + pen, a0))
        l1 = lane(cd + lane(v1 - m1, a0), a0)
        v2 = min(min(a2[r2, d + 1], j2), lane(min(a2[r2, d], a2[r2, d + 2]) + pen, a0))
        l2 = lane(cd + lane(v2 - m2, a0), a0)
        v3 = min(min(a3[r3, d + 1], j3), lane(min(a3[r3, d], a3[r3, d + 2]) + pen, a0))
        l3 = lane(cd + lane(v3 - m3, a0), a0)
        o0[w0, d + 1] = l0
        o1[w1, d + 1] = l1
        o2[w2, d + 1] = l2
        o3[w3, d + 1] = l3
        n0 = min(n0, l0)
        n1 = min(n1, l1)
        n2 = min(n2, l2)
        n3 = min(n3, l3)
    t_min = np.uint16(0xFFFF)
    for d in range(n_disp):
        pair01 = np.uint16(np.uint16(o0[w0, d + 1]) + np.uint16(o1[w1, d + 1]))
        pair23 = np.uint16(np.uint16(o2[w2, d + 1]) + np.uint16(o3[w3, d + 1]))
        total = np.uint16(base[by, bx, d] + np.uint16(pair01 + pair23))
        out[oy, ox, d] = total
        t_min = min(t_min, total)
    return np.uint16(n0), np.uint16(n1), np.uint16(n2), np.uint16(n3), t_min


@njit(cache=True, fastmath=FASTMATH, inline="always")
def step2(cost, y, x, base, by, bx, out, oy, ox, bufs, rows, pms, qs, p1):
    """Two-path version of :func:`step4` (the 4-path mode: horizontal + vertical); bufs = (a0, a1, o0, o1)."""
    n_disp = cost.shape[2]
    a0, a1, o0, o1 = bufs
    r0, r1, w0, w1 = rows
    pm0, pm1 = pms
    pen = lane(p1, a0)
    j0 = lane(pm0 + qs[0], a0)
    j1 = lane(pm1 + qs[1], a0)
    m0 = lane(pm0, a0)
    m1 = lane(pm1, a0)
    n0 = lane(0xFFFF, a0)
    n1 = n0
    for d in range(n_disp):
        cd = cost[y, x, d]
        v0 = min(min(a0[r0, d + 1], j0), lane(min(a0[r0, d], a0[r0, d + 2]) + pen, a0))
        l0 = lane(cd + lane(v0 - m0, a0), a0)
        v1 = min(min(a1[r1, d + 1], j1), lane(min(a1[r1, d], a1[r1, d + 2]) + pen, a0))
        l1 = lane(cd + lane(v1 - m1, a0), a0)
        o0[w0, d + 1] = l0
        o1[w1, d + 1] = l1
        n0 = min(n0, l0)
        n1 = min(n1, l1)
    t_min = np.uint16(0xFFFF)
    for d in range(n_disp):
        total = np.uint16(base[by, bx, d] + np.uint16(np.uint16(o0[w0, d + 1]) + np.uint16(o1[w1, d + 1])))
        out[oy, ox, d] = total
        t_min = min(t_min, total)
    return np.uint16(n0), np.uint16(n1), t_min


@njit(cache=True, fastmath=FASTMATH)
def _row_buffer(width, n_disp, lane_dtype, sentinel):
    """(W + 2, D + 2) zeroed buffer of the lane type with sentinels in slots 0 and D + 1 (the d +- 1 reads need no
    branch)."""
    buf = np.zeros((width + 2, n_disp + 2), dtype=lane_dtype)
    buf[:, 0] = sentinel
    buf[:, n_disp + 1] = sentinel
    return buf


@njit(cache=True, fastmath=FASTMATH)
def _buffers(width, n_disp, lane_dtype, sentinel):
    """Scratch of one sweep: previous- and current-row buffers of the 3 row paths (6 SEPARATE arrays, so LLVM's
    alias checks see distinct allocations), the horizontal ping-pong buffer (rows 0, 1; row 2 = the all-zero
    'outside the image' vector), the path minima (2 parities, 3 row paths, W + 2 columns) and a zero base."""
    even = (_row_buffer(width, n_disp, lane_dtype, sentinel), _row_buffer(width, n_disp, lane_dtype, sentinel),
            _row_buffer(width, n_disp, lane_dtype, sentinel))
    odd = (_row_buffer(width, n_disp, lane_dtype, sentinel), _row_buffer(width, n_disp, lane_dtype, sentinel),
           _row_buffer(width, n_disp, lane_dtype, sentinel))
    horiz = _row_buffer(1, n_disp, lane_dtype, sentinel)  # (3, D + 2)
    mins = np.zeros((2, 3, width + 2), dtype=np.uint16)
    zero = np.zeros((1, 1, n_disp), dtype=np.uint16)
    return even, odd, horiz, mins, zero


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _pixel(cost, grey, y, x, sy, p1, table, diag, prev, cur, horiz, mins, hmin, base, by, bx, out, oy, ox):
    """All paths of one sweep at pixel (y, x); sy = +1 forward (paths come from y - 1, x - 1), -1 backward.

    prev / cur: the 3 row-path buffers of the previous / current row (0: diagonal from the horizontal path's side,
    1: vertical, 2: anti-diagonal). Buffer columns run in sweep order (col = x + 1 forward, W - x backward; 0 and
    W + 1 are the zero borders): a backward sweep then walks its row buffers in ascending addresses too (descending
    walks over these MB-sized buffers measured 2-3x slower). In both sweeps the diagonal arriving from the
    horizontal path's side is at col - 1 and the anti-diagonal at col + 1. Returns the new horizontal-path minimum and
    the minimum over d of the written totals (the WTA's S_min in the backward sweep).
    """
    width = grey.shape[1]
    cur_p = y & 1
    prv_p = 1 - cur_p
    py = y - sy
    hx = x - sy  # previous pixel of the horizontal path
    col = x + 1 if sy > 0 else width - x
    hcur = x & 1
    first = hx < 0 or hx >= width
    hprev = 2 if first else 1 - hcur
    hpm = np.uint16(0) if first else hmin
    qh = penalty2(table, grey, y, x, y, hx)
    qv = penalty2(table, grey, y, x, py, x)
    if diag:
        qa = penalty2(table, grey, y, x, py, x - sy)
        qb = penalty2(table, grey, y, x, py, x + sy)
        nh, nv, na, nb, t_min = step4(cost, y, x, base, by, bx, out, oy, ox,
                               (horiz, prev[1], prev[0], prev[2], horiz, cur[1], cur[0], cur[2]),
                               (hprev, col, col - 1, col + 1, hcur, col, col, col),
                               (hpm, mins[prv_p, 1, col], mins[prv_p, 0, col - 1], mins[prv_p, 2, col + 1]),
                               (qh, qv, qa, qb), p1)
        mins[cur_p, 0, col] = na
        mins[cur_p, 2, col] = nb
    else:
        nh, nv, t_min = step2(cost, y, x, base, by, bx, out, oy, ox, (horiz, prev[1], horiz, cur[1]),
                       (hprev, col, hcur, col), (hpm, mins[prv_p, 1, col]), (qh, qv), p1)
    mins[cur_p, 1, col] = nv
    return nh, t_min


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _forward_row(cost, grey, y, p1, table, diag, prev, cur, horiz, mins, zero, s_out):
    """One row of the forward sweep. Called with a literal ``diag`` so that, once inlined, LLVM folds the 4- vs
    8-path branch out of the pixel loop (a runtime branch there cost ~25 ms per sweep on a KITTI frame)."""
    hmin = np.uint16(0)
    for x in range(grey.shape[1]):
        hmin, _ = _pixel(cost, grey, y, x, 1, p1, table, diag, prev, cur, horiz, mins, hmin, zero, 0, 0, s_out, y,
                         x)


@njit(cache=True, fastmath=FASTMATH, nogil=True)
def aggregate_forward(cost, grey, p1, p2, adaptive, diag, s_out, lane_dtype, sentinel):
    """Top-to-bottom sweep: left->right and top paths (plus top-left / top-right with ``diag``).

    Args:
        cost: (H, W, D) uint8 matching cost.
        grey: (H, W) uint8 image of this view (only read when ``adaptive``).
        p1, p2: SGM penalties; adaptive: P2 // max(1, |grad|) along each path, clamped to >= P1.
        diag: True for 8 paths in total (4 in this sweep), False for 4 (2 here).
        s_out: (H, W, D) uint16, receives the sum over this sweep's paths.
        lane_dtype, sentinel: type of the path costs and border sentinel, from ``_lanes.path_lanes``.
    """
    height, width, n_disp = cost.shape
    even, odd, horiz, mins, zero = _buffers(width, n_disp, lane_dtype, sentinel)
    table = p2_table(p1, p2, adaptive)
    for y in range(height):
        prev, cur = (odd, even) if y & 1 == 0 else (even, odd)
        if diag:
            _forward_row(cost, grey, y, p1, table, True, prev, cur, horiz, mins, zero, s_out)
        else:
            _forward_row(cost, grey, y, p1, table, False, prev, cur, horiz, mins, zero, s_out)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _backward_row(cost, grey, y, p1, table, diag, prev, cur, horiz, mins, s_fwd, acc, right_view, s_max, n_real, disp,
                  conf, uniq, ramp, want_uniq):
    """One row of the backward sweep with the fused WTA (literal ``diag``, see :func:`_forward_row`).

    s_fwd and cost are read in DESCENDING addresses here, which the hardware prefetcher follows poorly: the cache
    lines of the pixel PREFETCH_AHEAD columns ahead are requested explicitly (see _prefetch.py).
    """
    width = grey.shape[1]
    n_disp = cost.shape[2]
    s_addr = s_fwd.ctypes.data
    c_addr = cost.ctypes.data
    s_bytes = n_disp * 2
    hmin = np.uint16(0)
    for x in range(width - 1, -1, -1):
        ahead = y * width + x - PREFETCH_AHEAD
        if ahead >= 0:
            for offset in range(0, s_bytes, 64):
                prefetch(s_addr + ahead * s_bytes + offset)
            for offset in range(0, n_disp, 64):
                prefetch(c_addr + ahead * n_disp + offset)
        # S goes to the small `acc` (fixed indices, no aliasing with s_fwd in the hot loops: choosing the target
        # array per pixel cost ~4 ms per sweep); the tests rebuild the full S from _pixel (tests/kernel_refs.py).
        hmin, s_min = _pixel(cost, grey, y, x, -1, p1, table, diag, prev, cur, horiz, mins, hmin, s_fwd, y, x, acc,
                             0, 0)
        n_valid = width - x if right_view else x + 1
        disp[y, x], conf[y, x], uniq[y, x] = select_disparity(acc, 0, 0, n_real, n_valid, s_max, s_min, ramp,
                                                              want_uniq)


@njit(cache=True, fastmath=FASTMATH, nogil=True)
def aggregate_backward_wta(cost, grey, p1, p2, adaptive, diag, s_fwd, right_view, s_max, n_real, disp, conf, uniq,
                           lane_dtype, sentinel, want_uniq=True):
    """Bottom-to-top sweep of the mirrored paths, S = forward + backward, then WTA per pixel.

    Args:
        cost, grey, p1, p2, adaptive, diag: as in :func:`aggregate_forward`.
        s_fwd: (H, W, D) uint16 forward sums (read only; S itself is never stored, one pixel's S at a time).
        right_view, s_max: passed to :func:`wta.select_disparity` (with S_min, tracked while S is written).
        n_real: the disparities searched, [0, n_real); cost slots beyond it are padding (``_lanes.py``).
        disp, conf, uniq: (H, W) float32 outputs (uniq is 0 everywhere unless ``want_uniq``).
        lane_dtype, sentinel: as in :func:`aggregate_forward`.
        want_uniq: compute the uniqueness (one more pass over each pixel's S in the WTA).
    """
    height, width, n_disp = cost.shape
    even, odd, horiz, mins, _ = _buffers(width, n_disp, lane_dtype, sentinel)
    acc = np.empty((1, 1, n_disp), dtype=np.uint16)
    ramp = disparity_ramp(n_disp)
    table = p2_table(p1, p2, adaptive)
    for y in range(height - 1, -1, -1):
        prev, cur = (odd, even) if y & 1 == 0 else (even, odd)
        if diag:
            _backward_row(cost, grey, y, p1, table, True, prev, cur, horiz, mins, s_fwd, acc, right_view, s_max,
                          n_real, disp, conf, uniq, ramp, want_uniq)
        else:
            _backward_row(cost, grey, y, p1, table, False, prev, cur, horiz, mins, s_fwd, acc, right_view, s_max,
                          n_real, disp, conf, uniq, ramp, want_uniq)

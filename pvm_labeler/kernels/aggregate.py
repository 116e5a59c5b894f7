"""Numba SGM path aggregation (Hirschmueller 2008), one sweep per scan-direction family.

For a path direction r: L_r(p, d) = C(p, d) + min(L_r(p-r, d), L_r(p-r, d+-1) + P1, min_k L_r(p-r, k) + P2)
- min_k L_r(p-r, k); a path starts at the image border with L_r = C. S(p, d) = sum_r L_r(p, d).

* :func:`aggregate_forward` runs the paths that arrive from the left or from above (left->right and top, plus
  top-left and top-right with ``diag``) in one top-to-bottom sweep and stores their sum.
* :func:`aggregate_backward_wta` runs the mirrored paths bottom-to-top, adds the stored forward sum and calls the
  winner-takes-all of ``wta.py`` on each finished S vector, so the full S volume is read only once more.

Speed notes: all path arithmetic is uint16 with explicit casts (numba would widen to int64; uint16 lets LLVM use
16-lane AVX2 vpminuw/vpaddw), and the paths of a sweep are updated in ONE loop over d so C and S are touched once
per pixel. Only previous-row buffers (W + 2, D + 2) per path are kept, walked in ascending addresses by both
sweeps. The two extra disparity slots hold a
sentinel so the d +- 1 reads need no branch; the two extra columns stay zero (a path entering the image has L = C).
The wrapper guarantees L_r <= C_max + P2 < SENTINEL and n_paths * (C_max + P2) <= 65535, so nothing wraps.
"""

import numpy as np
from numba import njit

from pvm_labeler.kernels._flags import FASTMATH
from pvm_labeler.kernels._prefetch import prefetch
from pvm_labeler.kernels.wta import select_disparity

SENTINEL = 0x3FFF  # > any L_r, and SENTINEL + P1 still fits in uint16
PREFETCH_AHEAD = 4  # pixels; 2-16 measured alike on a KITTI frame (99-100 ms), 0 = no prefetch (142 ms)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def penalty2(p1, p2, adaptive, grey, y, x, py, px):
    """P2 for the step (py, px) -> (y, x); adaptive: P2 // max(1, |I(p) - I(p - r)|), never below P1."""
    if not adaptive or py < 0 or px < 0 or py >= grey.shape[0] or px >= grey.shape[1]:
        return np.uint16(p2)
    grad = abs(np.int32(grey[y, x]) - np.int32(grey[py, px]))
    return np.uint16(max(p1, p2 // max(np.int32(1), grad)))


# The recurrence is written out per path below on purpose: moving it into an inlined helper function makes
# LLVM give up on vectorizing the d loop (measured: 12x slower).


@njit(cache=True, fastmath=FASTMATH, inline="always")
def step4(cost, base, s_out, a0, a1, a2, a3, o0, o1, o2, o3, pm0, pm1, pm2, pm3, q0, q1, q2, q3, p1):
    """Four paths of one pixel in one pass: o_k[1:D+1] = L_k, s_out = base + sum_k L_k; returns the 4 minima.

    Args:
        cost: (D,) uint8; base, s_out: (D,) uint16 (may alias); a_k, o_k: (D + 2,) uint16 previous / new L_k
        with sentinels at 0 and D + 1; pm_k: min of a_k; q_k: P2 of path k (uint16); p1: P1.
    """
    n_disp = cost.shape[0]
    pen = np.uint16(p1)
    j0 = np.uint16(pm0 + q0)
    j1 = np.uint16(pm1 + q1)
    j2 = np.uint16(pm2 + q2)
    j3 = np.uint16(pm3 + q3)
    n0 = np.uint16(0xFFFF)
    n1 = n0
    n2 = n0
    n3 = n0
    for d in range(n_disp):
        cd = np.uint16(cost[d])
        v0 = min(min(a0[d + 1], j0), min(np.uint16(a0[d] + pen), np.uint16(a0[d + 2] + pen)))
        l0 = np.uint16(cd + np.uint16(v0 - pm0))
        v1 = min(min(a1[d + 1], j1), min(np.uint16(a1[d] + pen), np.uint16(a1[d + 2] + pen)))
        l1 = np.uint16(cd + np.uint16(v1 - pm1))
        v2 = min(min(a2[d + 1], j2), min(np.uint16(a2[d] + pen), np.uint16(a2[d + 2] + pen)))
        l2 = np.uint16(cd + np.uint16(v2 - pm2))
        v3 = min(min(a3[d + 1], j3), min(np.uint16(a3[d] + pen), np.uint16(a3[d + 2] + pen)))
        l3 = np.uint16(cd + np.uint16(v3 - pm3))
        o0[d + 1] = l0
        o1[d + 1] = l1
        o2[d + 1] = l2
        o3[d + 1] = l3
        s_out[d] = np.uint16(base[d] + np.uint16(np.uint16(l0 + l1) + np.uint16(l2 + l3)))
        n0 = min(n0, l0)
        n1 = min(n1, l1)
        n2 = min(n2, l2)
        n3 = min(n3, l3)
    return n0, n1, n2, n3


@njit(cache=True, fastmath=FASTMATH, inline="always")
def step2(cost, base, s_out, a0, a1, o0, o1, pm0, pm1, q0, q1, p1):
    """Two-path version of :func:`step4` (the 4-path mode: horizontal + vertical)."""
    n_disp = cost.shape[0]
    pen = np.uint16(p1)
    j0 = np.uint16(pm0 + q0)
    j1 = np.uint16(pm1 + q1)
    n0 = np.uint16(0xFFFF)
    n1 = n0
    for d in range(n_disp):
        cd = np.uint16(cost[d])
        v0 = min(min(a0[d + 1], j0), min(np.uint16(a0[d] + pen), np.uint16(a0[d + 2] + pen)))
        l0 = np.uint16(cd + np.uint16(v0 - pm0))
        v1 = min(min(a1[d + 1], j1), min(np.uint16(a1[d] + pen), np.uint16(a1[d + 2] + pen)))
        l1 = np.uint16(cd + np.uint16(v1 - pm1))
        o0[d + 1] = l0
        o1[d + 1] = l1
        s_out[d] = np.uint16(base[d] + np.uint16(l0 + l1))
        n0 = min(n0, l0)
        n1 = min(n1, l1)
    return n0, n1


@njit(cache=True, fastmath=FASTMATH)
def _buffers(width, n_disp):
    """Zeroed scratch: row buffers (2 parities, 3 row paths, W + 2 columns, D + 2 slots) with sentinels, their
    mins, the horizontal ping-pong buffers [0], [1] plus an all-zero 'outside the image' vector [2], and a zero
    (D,) base vector."""
    rows = np.zeros((2, 3, width + 2, n_disp + 2), dtype=np.uint16)
    rows[:, :, :, 0] = SENTINEL
    rows[:, :, :, n_disp + 1] = SENTINEL
    mins = np.zeros((2, 3, width + 2), dtype=np.uint16)
    horiz = np.zeros((3, n_disp + 2), dtype=np.uint16)
    horiz[:, 0] = SENTINEL
    horiz[:, n_disp + 1] = SENTINEL
    zero = np.zeros(n_disp, dtype=np.uint16)
    return rows, mins, horiz, zero


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _pixel(cost_px, grey, y, x, sy, p1, p2, adaptive, diag, rows, mins, horiz, hmin, base, s_out):
    """All paths of one sweep at pixel (y, x); sy = +1 forward (paths come from y - 1, x - 1), -1 backward.

    Buffer columns run in sweep order (col = x + 1 forward, W - x backward; 0 and W + 1 are the zero borders):
    a backward sweep then walks its row buffers in ascending addresses too (descending walks over these MB-sized
    buffers measured 2-3x slower). In both sweeps the diagonal arriving from the horizontal path's side is at
    col - 1 and the anti-diagonal at col + 1. Returns the new horizontal-path minimum.
    """
    width = grey.shape[1]
    cur = y & 1
    prv = 1 - cur
    py = y - sy
    hx = x - sy  # previous pixel of the horizontal path
    col = x + 1 if sy > 0 else width - x
    hcur = x & 1
    first = hx < 0 or hx >= width
    hprev = horiz[2] if first else horiz[1 - hcur]
    hpm = np.uint16(0) if first else hmin
    qh = penalty2(p1, p2, adaptive, grey, y, x, y, hx)
    qv = penalty2(p1, p2, adaptive, grey, y, x, py, x)
    if diag:
        qa = penalty2(p1, p2, adaptive, grey, y, x, py, x - sy)
        qb = penalty2(p1, p2, adaptive, grey, y, x, py, x + sy)
        nh, nv, na, nb = step4(cost_px, base, s_out, hprev, rows[prv, 1, col], rows[prv, 0, col - 1],
                               rows[prv, 2, col + 1], horiz[hcur], rows[cur, 1, col], rows[cur, 0, col],
                               rows[cur, 2, col], hpm, mins[prv, 1, col], mins[prv, 0, col - 1], mins[prv, 2, col + 1],
                               qh, qv, qa, qb, p1)
        mins[cur, 0, col] = na
        mins[cur, 2, col] = nb
    else:
        nh, nv = step2(cost_px, base, s_out, hprev, rows[prv, 1, col], horiz[hcur], rows[cur, 1, col], hpm,
                       mins[prv, 1, col], qh, qv, p1)
    mins[cur, 1, col] = nv
    return nh


@njit(cache=True, fastmath=FASTMATH)
def aggregate_forward(cost, grey, p1, p2, adaptive, diag, s_out):
    """Top-to-bottom sweep: left->right and top paths (plus top-left / top-right with ``diag``).

    Args:
        cost: (H, W, D) uint8 matching cost.
        grey: (H, W) uint8 image of this view (only read when ``adaptive``).
        p1, p2: SGM penalties; adaptive: P2 // max(1, |grad|) along each path, clamped to >= P1.
        diag: True for 8 paths in total (4 in this sweep), False for 4 (2 here).
        s_out: (H, W, D) uint16, receives the sum over this sweep's paths.
    """
    height, width, _ = cost.shape
    rows, mins, horiz, zero = _buffers(width, cost.shape[2])
    for y in range(height):
        hmin = np.uint16(0)
        for x in range(width):
            hmin = _pixel(cost[y, x], grey, y, x, 1, p1, p2, adaptive, diag, rows, mins, horiz, hmin, zero,
                          s_out[y, x])


@njit(cache=True, fastmath=FASTMATH)
def aggregate_backward_wta(cost, grey, p1, p2, adaptive, diag, s_fwd, store_sum, right_view, s_max, key_shift,
                           disp, conf, uniq):
    """Bottom-to-top sweep of the mirrored paths, S = forward + backward, then WTA per pixel.

    Args:
        cost, grey, p1, p2, adaptive, diag: as in :func:`aggregate_forward`.
        s_fwd: (H, W, D) uint16 forward sums; with ``store_sum`` it is overwritten by the full S (for tests).
        right_view, s_max, key_shift: passed to :func:`wta.select_disparity`.
        disp, conf, uniq: (H, W) float32 outputs.
    """
    height, width, n_disp = cost.shape
    rows, mins, horiz, _ = _buffers(width, n_disp)
    acc = np.empty(n_disp, dtype=np.uint16)
    # This sweep reads s_fwd and cost in descending addresses, which the hardware prefetcher follows poorly:
    # request the cache lines of the pixel PREFETCH_AHEAD columns ahead (see _prefetch.py).
    s_addr = s_fwd.ctypes.data
    c_addr = cost.ctypes.data
    s_bytes = n_disp * 2
    for y in range(height - 1, -1, -1):
        hmin = np.uint16(0)
        for x in range(width - 1, -1, -1):
            ahead = y * width + x - PREFETCH_AHEAD
            if ahead >= 0:
                for offset in range(0, s_bytes, 64):
                    prefetch(s_addr + ahead * s_bytes + offset)
                for offset in range(0, n_disp, 64):
                    prefetch(c_addr + ahead * n_disp + offset)
            total = s_fwd[y, x] if store_sum else acc
            hmin = _pixel(cost[y, x], grey, y, x, -1, p1, p2, adaptive, diag, rows, mins, horiz, hmin, s_fwd[y, x],
                          total)
            n_valid = width - x if right_view else x + 1
            disp[y, x], conf[y, x], uniq[y, x] = select_disparity(total, n_valid, s_max, key_shift)

"""Numba SGM path aggregation (Hirschmueller 2008), one sweep per scan-direction family.

For a path direction r: L_r(p, d) = C(p, d) + min(L_r(p-r, d), L_r(p-r, d+-1) + P1, min_k L_r(p-r, k) + P2)
- min_k L_r(p-r, k); a path starts at the image border with L_r = C. S(p, d) = sum_r L_r(p, d).

* :func:`aggregate_forward` runs the paths that arrive from above or from the left (left->right, and with
  ``diag`` top-left, top, top-right; otherwise only top) in one top-to-bottom sweep and stores their sum.
* :func:`aggregate_backward_wta` runs the mirrored paths bottom-to-top, adds the stored forward sum and calls the
  winner-takes-all of ``wta.py`` on the finished S row by row, so the full S volume is never re-read.

Everything is uint16 (costs are bounded: L_r <= C_max + P2, checked by the wrapper) so LLVM packs 16 lanes per
AVX2 instruction; only previous-row buffers (W + 2, D + 2) per path are kept. The two extra disparity slots hold a
large sentinel so that the d +- 1 reads need no branch; the two extra columns stay zero (a path entering the image
has L = C).
"""

import numpy as np
from numba import njit

from pvm_labeler.kernels._flags import FASTMATH
from pvm_labeler.kernels.wta import select_disparity

SENTINEL = 0x3FFF  # > any L_r, and SENTINEL + P1 still fits in uint16 (the wrapper checks C_max + P2 < SENTINEL)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _penalty2(p1, p2, adaptive, grey, y, x, py, px):
    """P2 for the step (py, px) -> (y, x); adaptive: P2 / max(1, |I(p) - I(p - r)|), never below P1."""
    if not adaptive or py < 0 or px < 0 or py >= grey.shape[0] or px >= grey.shape[1]:
        return p2
    grad = abs(np.int32(grey[y, x]) - np.int32(grey[py, px]))
    return max(p1, p2 // max(np.int32(1), grad))


@njit(cache=True, fastmath=FASTMATH, inline="always")
def path_step(cost, prev, prev_min, p1, p2, out, acc):
    """One SGM step along a path for one pixel; adds L_r into ``acc`` and returns min_d L_r.

    Args:
        cost: (D,) uint8 matching cost C(p, .).
        prev: (D + 2,) uint16 L_r(p - r, .) at [1 : D + 1], sentinels at 0 and D + 1.
        prev_min: min_d L_r(p - r, d).
        p1, p2: penalties (p2 >= p1).
        out: (D + 2,) uint16, receives L_r(p, .) at [1 : D + 1].
        acc: (D,) uint16 running sum over paths.
    """
    n_disp = cost.shape[0]
    pm = np.uint16(prev_min)
    jump = np.uint16(pm + np.uint16(p2))
    pen = np.uint16(p1)
    new_min = np.uint16(0xFFFF)
    for d in range(n_disp):
        v = min(min(prev[d + 1], jump), min(np.uint16(prev[d] + pen), np.uint16(prev[d + 2] + pen)))
        val = np.uint16(np.uint16(cost[d]) + np.uint16(v - pm))
        out[d + 1] = val
        acc[d] = np.uint16(acc[d] + val)
        new_min = min(new_min, val)
    return new_min


@njit(cache=True, fastmath=FASTMATH)
def _buffers(width, n_disp):
    """Zeroed scratch: row buffers (2 parities, 3 row paths, W + 2 columns, D + 2 slots) with sentinels, their
    mins, the horizontal ping-pong buffers plus an always-zero 'outside the image' vector, and the path sum."""
    rows = np.zeros((2, 3, width + 2, n_disp + 2), dtype=np.uint16)
    rows[:, :, :, 0] = SENTINEL
    rows[:, :, :, n_disp + 1] = SENTINEL
    mins = np.zeros((2, 3, width + 2), dtype=np.uint16)
    horiz = np.zeros((3, n_disp + 2), dtype=np.uint16)  # [0], [1]: ping-pong; [2]: all-zero 'outside' vector
    horiz[:, 0] = SENTINEL
    horiz[:, n_disp + 1] = SENTINEL
    acc = np.zeros(n_disp, dtype=np.uint16)
    return rows, mins, horiz, acc


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _row_paths(cost_px, grey, y, x, step_y, step_x, p1, p2, adaptive, diag, rows, mins, cur, prv, acc):
    """The (up to) three row-to-row paths of one pixel; step_y = +1 for the forward sweep, -1 backward."""
    py = y - step_y
    # path 1: straight vertical, from (py, x)
    pen2 = _penalty2(p1, p2, adaptive, grey, y, x, py, x)
    mins[cur, 1, x + 1] = path_step(cost_px, rows[prv, 1, x + 1], mins[prv, 1, x + 1], p1, pen2, rows[cur, 1, x + 1], acc)
    if diag:
        # path 0: from (py, x - step_x); path 2: from (py, x + step_x); buffer column index = image column + 1
        pa = x - step_x
        pen2 = _penalty2(p1, p2, adaptive, grey, y, x, py, pa)
        mins[cur, 0, x + 1] = path_step(cost_px, rows[prv, 0, pa + 1], mins[prv, 0, pa + 1], p1, pen2,
                                        rows[cur, 0, x + 1], acc)
        pb = x + step_x
        pen2 = _penalty2(p1, p2, adaptive, grey, y, x, py, pb)
        mins[cur, 2, x + 1] = path_step(cost_px, rows[prv, 2, pb + 1], mins[prv, 2, pb + 1], p1, pen2,
                                        rows[cur, 2, x + 1], acc)


@njit(cache=True, fastmath=FASTMATH)
def aggregate_forward(cost, grey, p1, p2, adaptive, diag, s_out):
    """Top-to-bottom sweep: left->right and top paths (plus top-left / top-right with ``diag``).

    Args:
        cost: (H, W, D) uint8 matching cost.
        grey: (H, W) uint8 image of this view (only read when ``adaptive``).
        p1, p2: SGM penalties; adaptive: P2 / max(1, |grad|) along each path, clamped to >= P1.
        diag: True for 8 paths in total (4 here), False for 4 (2 here).
        s_out: (H, W, D) uint16, receives the sum over this sweep's paths.
    """
    height, width, n_disp = cost.shape
    rows, mins, horiz, acc = _buffers(width, n_disp)
    for y in range(height):
        cur = y & 1
        prv = 1 - cur
        hmin = np.uint16(0)
        for x in range(width):
            cost_px = cost[y, x]
            acc[:] = 0
            hcur = x & 1
            hprev = horiz[2] if x == 0 else horiz[1 - hcur]
            pen2 = _penalty2(p1, p2, adaptive, grey, y, x, y, x - 1)
            hmin = path_step(cost_px, hprev, hmin if x > 0 else np.uint16(0), p1, pen2, horiz[hcur], acc)
            _row_paths(cost_px, grey, y, x, 1, 1, p1, p2, adaptive, diag, rows, mins, cur, prv, acc)
            s_out[y, x] = acc


@njit(cache=True, fastmath=FASTMATH)
def aggregate_backward_wta(cost, grey, p1, p2, adaptive, diag, s_fwd, store_sum, right_view, s_max, key_shift,
                           disp, conf, uniq):
    """Bottom-to-top sweep of the mirrored paths, S = forward + backward, then WTA per pixel.

    Args:
        cost, grey, p1, p2, adaptive, diag: as in :func:`aggregate_forward`.
        s_fwd: (H, W, D) uint16 forward sums; with ``store_sum`` it is overwritten by the full S (tests only).
        right_view, s_max, key_shift: passed to :func:`wta.select_disparity`.
        disp, conf, uniq: (H, W) float32 outputs.
    """
    height, width, n_disp = cost.shape
    rows, mins, horiz, acc = _buffers(width, n_disp)
    for y in range(height - 1, -1, -1):
        cur = y & 1
        prv = 1 - cur
        hmin = np.uint16(0)
        for x in range(width - 1, -1, -1):
            cost_px = cost[y, x]
            acc[:] = s_fwd[y, x]
            hcur = x & 1
            hprev = horiz[2] if x == width - 1 else horiz[1 - hcur]
            pen2 = _penalty2(p1, p2, adaptive, grey, y, x, y, x + 1)
            hmin = path_step(cost_px, hprev, hmin if x < width - 1 else np.uint16(0), p1, pen2, horiz[hcur], acc)
            _row_paths(cost_px, grey, y, x, -1, -1, p1, p2, adaptive, diag, rows, mins, cur, prv, acc)
            if store_sum:
                s_fwd[y, x] = acc
            n_valid = width - x if right_view else x + 1
            disp[y, x], conf[y, x], uniq[y, x] = select_disparity(acc, n_valid, s_max, key_shift)

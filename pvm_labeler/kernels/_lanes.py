"""The integer type of the SGM path costs, chosen per call: uint8 when every intermediate fits, else uint16.

Why: on AVX2 a 256-bit vector holds 32 uint8 lanes but only 16 uint16 lanes, so the path recurrence runs on
twice the disparities per instruction in uint8 (KITTI frame, D = 192, one thread: forward sweep 81 -> 66 ms,
backward sweep + WTA 108 -> 72 ms, identical results; see docs/sgm.md). The aggregated sum S stays uint16.

Bounds (C_max = largest census cost, 0 <= P1 <= P2, previous path vector a with minimum m): every candidate of
the recurrence is at least m, so v - m never wraps; L_r = C + v - m lies in [C, C + P2], and at the previous
minimum's d it is C <= C_max, so m <= C_max and the P2 candidate m + P2 <= C_max + P2. The largest intermediate
is a neighbour candidate a(d +- 1) + P1 <= C_max + P2 + P1, and the border sentinel 255 - P1 still exceeds every
L_r. uint8 therefore needs C_max + P1 + P2 <= 255 (5x5 census, P1 = 8: P2 <= 223).
"""

import numpy as np
from numba import types
from numba.extending import overload

from pvm_labeler.config import PATH_SENTINEL

SENTINEL16 = PATH_SENTINEL  # > any L_r LabelerConfig.validate allows, and SENTINEL16 + P1 still fits in uint16


def path_lanes(c_max: int, p1: int, p2: int) -> tuple[type, int]:
    """(numpy integer type of the path costs, border sentinel) for census cost C_max and penalties P1 <= P2."""
    if c_max + p1 + p2 <= 0xFF:
        return np.uint8, 0xFF - p1  # >= C_max + P2 (>= any L_r), and sentinel + P1 = 255 does not wrap
    return np.uint16, SENTINEL16


def lane(value, like):  # pragma: no cover - replaced by the numba overload below
    """Cast ``value`` to the dtype of the array ``like`` (uint8 or uint16); numba-only."""
    raise NotImplementedError("lane() is only callable from numba-compiled code")


@overload(lane, inline="always")
def _lane_overload(value, like):
    if like.dtype == types.uint8:
        return lambda value, like: np.uint8(value)
    return lambda value, like: np.uint16(value)


DISPARITY_BLOCK = 32  # uint8 lanes per AVX2 vector


def disparity_padding(c_max: int, p1: int, p2: int, n_disp: int) -> tuple[int, int]:
    """(padded number of disparities, cost of the padded slots); (n_disp, 0) when padding does not apply.

    Why: the vectorised loops over d leave a scalar remainder when D is not a multiple of the vector width, and
    the pyramid's coarse scales have such D (ceil(192 / factor): 138, 99, 71, ...). Measured on KITTI-sized scales,
    one thread: D = 138 -> 167 ms but D = 160 -> 141 ms; 99 -> 70 ms, 128 -> 64 ms; 71 -> 33 ms, 96 -> 27 ms. So
    the volumes get D rounded up to DISPARITY_BLOCK, and the extra slots the cost C_pad = C_max + P2 + 1.

    Exactness (every real d gives the same L_r, S and WTA): a path cost lies in [C, C + P2], so padded L_r >= C_pad
    > C_max + P2 >= every real L_r. The path minimum stays at a real d (at the previous minimum's d, L_r = C <=
    C_max), so min_k L_r is unchanged; the only padded value a real d reads, L_r(D) + P1 >= C_pad, never beats the
    P2 candidate min_k L_r + P2 <= C_max + P2. Padded S >= n_paths * C_pad > every real S_min, and the WTA searches
    the real d only. Only with uint8 lanes: padded L_r + P1 <= C_max + 2 P2 + 1 + P1 must fit in 255 (the sentinel
    255 - P1 then still exceeds every L_r).
    """
    if c_max + p1 + 2 * p2 + 1 > 0xFF or n_disp % DISPARITY_BLOCK == 0:
        return n_disp, 0
    return -(-n_disp // DISPARITY_BLOCK) * DISPARITY_BLOCK, c_max + p2 + 1

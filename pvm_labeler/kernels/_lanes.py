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

SENTINEL16 = 0x3FFF  # > any L_r the wrapper allows, and SENTINEL16 + P1 still fits in uint16


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

"""Slow pure-NumPy references of the SGM kernels (census, cost volume, right-view re-indexing, path aggregation,
WTA + sub-pixel); the numba kernels in pvm_labeler/kernels must match them exactly (integers) or to float32
rounding."""

from __future__ import annotations

import numpy as np

# Path directions r = (dy, dx): the path reaches p from p - r.
FORWARD_PATHS_8 = ((0, 1), (1, 0), (1, 1), (1, -1))
BACKWARD_PATHS_8 = ((0, -1), (-1, 0), (-1, -1), (-1, 1))
FORWARD_PATHS_4 = ((0, 1), (1, 0))
BACKWARD_PATHS_4 = ((0, -1), (-1, 0))


def naive_census(img: np.ndarray, window: int) -> np.ndarray:
    """Census codes (H, W) uint64: bits in raster order of the window (centre skipped), MSB first; a bit is 1 when
    the neighbour (clamped to the image) is darker than the centre."""
    height, width = img.shape
    r = window // 2
    code = np.zeros((height, width), dtype=np.uint64)
    ys = np.arange(height)[:, None]
    xs = np.arange(width)[None, :]
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy == 0 and dx == 0:
                continue
            nb = img[np.clip(ys + dy, 0, height - 1), np.clip(xs + dx, 0, width - 1)]
            code = (code << np.uint64(1)) | (nb < img).astype(np.uint64)
    return code


def naive_cost_volume(census_left: np.ndarray, census_right: np.ndarray, n_disp: int, invalid_cost: int) -> np.ndarray:
    """C(y, x, d) = popcount(census_left[y, x] ^ census_right[y, x - d]), invalid_cost where x < d; (H, W, D) uint8."""
    height, width = census_left.shape
    cost = np.full((height, width, n_disp), invalid_cost, dtype=np.uint8)
    for d in range(n_disp):
        xor = census_left[:, d:] ^ census_right[:, : width - d]
        cost[:, d:, d] = np.vectorize(lambda v: int(v).bit_count(), otypes=[np.uint8])(xor)
    return cost


def naive_reindex_right(cost_left: np.ndarray, invalid_cost: int) -> np.ndarray:
    """C_r(y, x, d) = C_l(y, x + d, d), invalid_cost where x + d >= W."""
    height, width, n_disp = cost_left.shape
    out = np.full_like(cost_left, invalid_cost)
    for d in range(n_disp):
        out[:, : width - d, d] = cost_left[:, d:, d]
    return out


def naive_penalty2(grey: np.ndarray | None, p1: int, p2: int, y: int, x: int, py: int, px: int) -> int:
    """P2 of the step (py, px) -> (y, x): P2 // max(1, |grad|), clamped to >= P1 (plain P2 without ``grey``)."""
    if grey is None:
        return p2
    grad = abs(int(grey[y, x]) - int(grey[py, px]))
    return max(p1, p2 // max(1, grad))


def naive_path(cost: np.ndarray, direction: tuple[int, int], p1: int, p2: int,
               grey: np.ndarray | None = None) -> np.ndarray:
    """L_r for one direction r = (dy, dx), pixel by pixel in the path order; (H, W, D) int64.

    L_r(p, d) = C(p, d) + min(L(p-r, d), L(p-r, d-+1) + P1, min_k L(p-r, k) + P2) - min_k L(p-r, k);
    L_r(p) = C(p) when p - r lies outside the image.
    """
    height, width, n_disp = cost.shape
    dy, dx = direction
    out = np.zeros(cost.shape, dtype=np.int64)
    ys = range(height) if dy >= 0 else range(height - 1, -1, -1)
    xs = list(range(width)) if dx >= 0 else list(range(width - 1, -1, -1))
    big = 1 << 40
    for y in ys:
        for x in xs:
            py, px = y - dy, x - dx
            c = cost[y, x].astype(np.int64)
            if not (0 <= py < height and 0 <= px < width):
                out[y, x] = c
                continue
            prev = out[py, px]
            pmin = prev.min()
            q2 = naive_penalty2(grey, p1, p2, y, x, py, px)
            lower = np.concatenate(([big], prev[:-1])) + p1
            upper = np.concatenate((prev[1:], [big])) + p1
            best = np.minimum.reduce([prev, lower, upper, np.full(n_disp, pmin + q2)])
            out[y, x] = c + best - pmin
    return out


def naive_aggregate(cost: np.ndarray, directions: tuple[tuple[int, int], ...], p1: int, p2: int,
                    grey: np.ndarray | None = None) -> np.ndarray:
    """S = sum of naive_path over ``directions``; (H, W, D) int64."""
    return sum(naive_path(cost, r, p1, p2, grey) for r in directions)


def naive_wta(cost_sum: np.ndarray, right_view: bool, s_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """WTA on S (H, W, D): disparity with parabola fit, c = clip(1 - S_min / s_max, 0, 1), uniqueness
    1 - S_min / min_{|d - d*| > 1} S; NaN / 0 / 0 where d* has no partner (x - d* < 0, or x + d* >= W for the
    right view) or ties with some |d - d*| > 1. Ties within d* + 1 go to the smallest d.

    Returns:
        disp, conf, uniq: (H, W) float32.
    """
    height, width, n_disp = cost_sum.shape
    disp = np.full((height, width), np.nan, dtype=np.float32)
    conf = np.zeros((height, width), dtype=np.float32)
    uniq = np.zeros((height, width), dtype=np.float32)
    for y in range(height):
        for x in range(width):
            s = cost_sum[y, x].astype(np.float64)
            d = int(np.argmin(s))
            n_valid = width - x if right_view else x + 1
            if d >= n_valid:
                continue
            others = np.concatenate((s[: max(d - 1, 0)], s[d + 2 :]))
            if others.size and others.min() == s[d]:
                continue  # not unique
            offset = 0.0
            if 0 < d < n_disp - 1:
                denom = s[d - 1] - 2 * s[d] + s[d + 1]
                if denom > 0:
                    offset = (s[d - 1] - s[d + 1]) / (2 * denom)
            disp[y, x] = d + offset
            conf[y, x] = min(max(1.0 - s[d] / s_max, 0.0), 1.0)
            if others.size and others.min() > 0:
                uniq[y, x] = 1.0 - s[d] / others.min()
    return disp, conf, uniq


def naive_lr_check(disp_left: np.ndarray, disp_right: np.ndarray, threshold: float) -> np.ndarray:
    """Keep left pixels whose right partner x - round(d) agrees within ``threshold`` px; others NaN (test helper)."""
    height, width = disp_left.shape
    out = np.full_like(disp_left, np.nan)
    ys, xs = np.nonzero(np.isfinite(disp_left))
    xr = np.rint(xs - disp_left[ys, xs]).astype(np.int64)
    inside = (xr >= 0) & (xr < width)
    ys, xs, xr = ys[inside], xs[inside], xr[inside]
    ok = np.abs(disp_left[ys, xs] - disp_right[ys, xr]) <= threshold
    out[ys[ok], xs[ok]] = disp_left[ys[ok], xs[ok]]
    return out


def naive_weighted_median(disp: np.ndarray, image: np.ndarray, radius: int, sigma: float,
                          min_range: float) -> np.ndarray:
    """Colour-weighted median, pixel by pixel: window values sorted, the first whose cumulative weight reaches half
    the total; windows spanning <= min_range px (and all-NaN windows) keep the centre. (H, W) float32."""
    height, width = disp.shape
    guide = image.astype(np.float64)
    out = disp.copy()
    for y in range(height):
        for x in range(width):
            ys, xs = slice(max(0, y - radius), y + radius + 1), slice(max(0, x - radius), x + radius + 1)
            values = disp[ys, xs].ravel()
            dist2 = ((guide[ys, xs] - guide[y, x]) ** 2).sum(-1).ravel()
            keep = np.isfinite(values)
            if not keep.any():
                continue
            if np.isfinite(disp[y, x]) and values[keep].max() - values[keep].min() <= min_range:
                continue
            values, weights = values[keep], np.exp(-dist2[keep] / (2 * sigma**2))
            order = np.argsort(values, kind="stable")
            cum = np.cumsum(weights[order])
            out[y, x] = values[order][np.searchsorted(cum, cum[-1] / 2)]
    return out

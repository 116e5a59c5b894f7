"""Slow pure-NumPy references for the PVM voting and LR-check kernels (tests compare the numba kernels to these)."""

from __future__ import annotations

import numpy as np


def naive_vote(
    disp: np.ndarray, conf: np.ndarray, kappa1: float, kappa2: float, label_mode: str = "finest",
    weights: np.ndarray | None = None, c2_scale: float = 0.6,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reference voting with np.std / np.median over the scale axis.

    Args:
        disp: (K, H, W) float32 full-resolution disparities, NaN = invalid.
        conf: (K, H, W) float32 normalized inverse costs, NaN = invalid.
        kappa1, kappa2: thresholds on C1 = std_k disp and C2 = std_k conf (keep iff C1 < kappa1 and C2 < kappa2).
        label_mode: "finest" (D^1), "median", "mean" or "weighted" (with ``weights``).
        weights: (K,) scale weights for "weighted".
        c2_scale: normaliser of C2 in the confidence mean c * (1 - C1 / kappa1) * (1 - C2 / c2_scale).

    Returns:
        label (H, W) float32 (NaN = rejected), confidence (H, W) float32 (0 = rejected), C1, C2 (H, W) float32
        (NaN where some scale is invalid).
    """
    d64 = disp.astype(np.float64)
    c64 = conf.astype(np.float64)
    all_valid = np.all(np.isfinite(d64) & np.isfinite(c64), axis=0)
    with np.errstate(invalid="ignore"):
        c1 = np.std(d64, axis=0)
        c2 = np.std(c64, axis=0)
    c1[~all_valid] = np.nan
    c2[~all_valid] = np.nan
    with np.errstate(invalid="ignore"):
        keep = all_valid & (c1 < kappa1) & (c2 < kappa2)
    if label_mode == "finest":
        value = d64[0]
    elif label_mode == "median":
        value = np.median(d64, axis=0)
    elif label_mode == "mean":
        value = np.mean(d64, axis=0)
    elif label_mode == "weighted":
        w = np.asarray(weights, dtype=np.float64)[:, None, None]
        value = np.sum(w * d64, axis=0) / np.sum(w)
    else:
        raise ValueError(f"unknown label_mode {label_mode!r}")
    label = np.where(keep, value, np.nan).astype(np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        score = np.mean(c64, axis=0) * (1.0 - c1 / kappa1) * (1.0 - c2 / c2_scale)
    confidence = np.where(keep, np.clip(score, 0.0, 1.0), 0.0).astype(np.float32)
    return label, confidence, c1.astype(np.float32), c2.astype(np.float32)


def naive_lr_check(disp_l: np.ndarray, disp_r: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Reference LRDCC with explicit Python loops and rounded (nearest-column) look-ups.

    Args:
        disp_l: (H, W) float32 left disparity, left(x) matches right(x - d); NaN = none.
        disp_r: (H, W) float32 right disparity, right(x) matches left(x + d); NaN = none.
        threshold: pixels.

    Returns:
        (left, right) (H, W) float32 copies with inconsistent pixels set to NaN.
    """
    height, width = disp_l.shape
    out_l = np.full_like(disp_l, np.nan)
    out_r = np.full_like(disp_r, np.nan)
    for y in range(height):
        for x in range(width):
            d = disp_l[y, x]
            if np.isfinite(d):
                xr = int(np.floor(float(x) - float(d) + 0.5))
                if 0 <= xr < width and np.isfinite(disp_r[y, xr]) and abs(d - disp_r[y, xr]) <= threshold:
                    out_l[y, x] = d
            d = disp_r[y, x]
            if np.isfinite(d):
                xl = int(np.floor(float(x) + float(d) + 0.5))
                if 0 <= xl < width and np.isfinite(disp_l[y, xl]) and abs(d - disp_l[y, xl]) <= threshold:
                    out_r[y, x] = d
    return out_l, out_r

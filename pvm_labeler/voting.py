"""Variance voting over the scales and the left-right consistency check: numpy wrappers of the numba kernels."""

from __future__ import annotations

import numpy as np

from pvm_labeler.common.errors import InputError
from pvm_labeler.config import LabelerConfig
from pvm_labeler.kernels.lrcheck import lr_check_kernel
from pvm_labeler.kernels.vote import LABEL_MEDIAN, LABEL_WEIGHTED, vote_kernel


def vote(
    disp: np.ndarray, conf: np.ndarray, cfg: LabelerConfig, factors: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Variance voting over the scales (wrapper of ``kernels.vote.vote_kernel``).

    Args:
        disp: (K, H, W) float32 full-resolution disparities (NaN = invalid).
        conf: (K, H, W) float32 full-resolution c maps (NaN = invalid).
        cfg: uses kappa1, kappa2, label_mode.
        factors: (K,) true factors, needed for label_mode "weighted" (weights 1 / factor_k**2: the disparity
            quantisation noise of scale k grows with its factor).

    Returns:
        label (H, W) float32 (NaN = rejected), confidence (H, W) float32 (0 = rejected), C1, C2 (H, W) float32.
    """
    if disp.ndim != 3 or disp.shape != conf.shape:
        raise InputError(f"disp/conf must be (K, H, W) of equal shape, got {disp.shape} and {conf.shape}")
    n = disp.shape[0]
    weights = np.zeros(n, dtype=np.float64)
    mode = LABEL_WEIGHTED
    if cfg.label_mode == "finest":
        weights[0] = 1.0
    elif cfg.label_mode == "mean":
        weights[:] = 1.0
    elif cfg.label_mode == "weighted":
        if factors is None or len(factors) != n:
            raise InputError(f"label_mode 'weighted' needs {n} scale factors, got {factors}")
        weights[:] = 1.0 / np.asarray(factors, dtype=np.float64) ** 2
    else:
        mode = LABEL_MEDIAN
    disp = np.ascontiguousarray(disp, dtype=np.float32)
    conf = np.ascontiguousarray(conf, dtype=np.float32)
    shape = disp.shape[1:]
    label = np.empty(shape, np.float32)
    confidence = np.empty(shape, np.float32)
    c1 = np.empty(shape, np.float32)
    c2 = np.empty(shape, np.float32)
    vote_kernel(disp, conf, float(cfg.kappa1), float(cfg.kappa2), float(cfg.c2_scale), mode, weights, label, confidence,
                c1, c2)
    return label, confidence, c1, c2


def lr_check(disp_l: np.ndarray, disp_r: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """LRDCC of a left and a right disparity map (wrapper of ``kernels.lrcheck.lr_check_kernel``).

    Args:
        disp_l: (H, W) float32 left disparity (left(x) matches right(x - d)), NaN = none.
        disp_r: (H, W) float32 right disparity (right(x) matches left(x + d)), NaN = none.
        threshold: pixels, >= 0.

    Returns:
        (left, right) (H, W) float32 with pixels failing the check set to NaN.
    """
    if disp_l.ndim != 2 or disp_l.shape != disp_r.shape:
        raise InputError(f"left/right disparities must be (H, W) of equal shape, got {disp_l.shape}, {disp_r.shape}")
    if not threshold >= 0:
        raise InputError(f"LR threshold must be >= 0 px, got {threshold}")
    disp_l = np.ascontiguousarray(disp_l, dtype=np.float32)
    disp_r = np.ascontiguousarray(disp_r, dtype=np.float32)
    out_l = np.empty_like(disp_l)
    out_r = np.empty_like(disp_r)
    lr_check_kernel(disp_l, disp_r, float(threshold), out_l, out_r)
    return out_l, out_r

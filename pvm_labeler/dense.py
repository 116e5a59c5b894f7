"""Dense left-view SGM: the labeler's matcher at full resolution, no LR check, no filtering, holes filled by the
nearest valid value on their row. The baseline the network must beat (the evaluation's ``dense_sgm``, used by
pipelines/studies/: train_pretrained.py, error_regions.py, refine_study.py, train_studies.py) and, filtered, the hole
fill of
``pvm-label densify --method sgm``."""

from __future__ import annotations

import time

import numpy as np

from pvm_labeler.config import LabelerConfig
from pvm_labeler.multiscale import _to_grey
from pvm_labeler.sgm import sgm_pair


def fill_rows_nearest(disp: np.ndarray) -> np.ndarray:
    """Fill NaN pixels with the nearest finite value on the same row (the closer side; the left one on ties).

    disp: (H, W) float32, NaN = no value. Rows without any finite value stay NaN.
    """
    height, width = disp.shape
    finite = np.isfinite(disp)
    cols = np.broadcast_to(np.arange(width), (height, width))
    left_idx = np.maximum.accumulate(np.where(finite, cols, -1), axis=1)  # last finite column at or before x
    right_idx = np.minimum.accumulate(np.where(finite, cols, width)[:, ::-1], axis=1)[:, ::-1]  # first at/after x
    use_left = (left_idx >= 0) & ((right_idx >= width) | (cols - left_idx <= right_idx - cols))
    src = np.where(use_left, left_idx, right_idx)
    has = (src >= 0) & (src < width)
    rows = np.broadcast_to(np.arange(height)[:, None], (height, width))
    out = np.full_like(disp, np.nan)
    out[has] = disp[rows[has], src[has]]
    return out


def sgm_left(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, max_disp: int | None = None
             ) -> tuple[np.ndarray, float]:
    """(left-view SGM disparity (H, W) float32 with NaN where SGM gives none, seconds) for an (H, W, 3) uint8 pair."""
    t0 = time.perf_counter()
    res, _ = sgm_pair(_to_grey(left, "left"), _to_grey(right, "right"), cfg, max_disp=max_disp, right_view=False)
    return res.disp, time.perf_counter() - t0


def sgm_views(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, max_disp: int | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """(left-view, right-view) SGM disparity, (H, W) float32 with NaN where SGM gives none, of an (H, W, 3) uint8
    pair from ONE census cost volume (the labeler's own right view: right(x) matches left(x + d))."""
    res_l, res_r = sgm_pair(_to_grey(left, "left"), _to_grey(right, "right"), cfg, max_disp=max_disp,
                            right_view=True)
    return res_l.disp, res_r.disp


#: Search range of a GT set that states none and a pair that records none (the eval's dense-SGM baseline).
FALLBACK_MAX_DISP = 64


def dense_sgm(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, set_max_disp: int | None,
              pair_max_disp: int | None = None) -> tuple[np.ndarray, float]:
    """The evaluation's dense-SGM baseline of one pair: :func:`sgm_left` over the set's search range (else the
    pair's own, else FALLBACK_MAX_DISP), holes filled along the row. Returns ((H, W) float32, seconds of SGM)."""
    disp, seconds = sgm_left(left, right, cfg, set_max_disp or pair_max_disp or FALLBACK_MAX_DISP)
    return fill_rows_nearest(disp), seconds

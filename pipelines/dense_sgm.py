"""Dense SGM, the baseline the network must beat: the labeler's own matcher at full resolution, left view, no LR check,
no filtering, and holes (NaN) filled by the nearest valid value on their row. Used by the training studies and by
the shipped model's evaluation (pipelines/train_studies.py, pipelines/train_pretrained.py)."""

from __future__ import annotations

import numpy as np

from pvm_labeler.config import LabelerConfig
from pvm_labeler.dense import fill_rows_nearest, sgm_left

__all__ = ["FALLBACK_MAX_DISP", "dense_sgm", "fill_rows_nearest", "sgm_left"]


#: Search range of a GT set that states none and a pair that records none (the eval's dense-SGM baseline).
FALLBACK_MAX_DISP = 64


def dense_sgm(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, set_max_disp: int | None,
              pair_max_disp: int | None = None) -> tuple[np.ndarray, float]:
    """The evaluation's dense-SGM baseline of one pair: :func:`sgm_left` over the set's search range (else the
    pair's own, else FALLBACK_MAX_DISP), holes filled along the row. Returns ((H, W) float32, seconds of SGM)."""
    disp, seconds = sgm_left(left, right, cfg, set_max_disp or pair_max_disp or FALLBACK_MAX_DISP)
    return fill_rows_nearest(disp), seconds

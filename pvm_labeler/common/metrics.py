"""Disparity metrics in NumPy: THE ruler shared by the labeler report and the network evaluator.

Definitions (over GT-valid pixels V = finite(gt) & valid; the readers already map "0 = no GT" codes to NaN):

- ``n_valid`` = |V|; ``n_covered`` = |V & finite(pred)|; ``density`` = 100 * n_covered / n_valid (%).
- On covered pixels, err = |pred - gt|: ``epe`` = mean(err) (AEPE, px); ``bad1``/``bad2``/``bad3`` =
  100 * mean(err > N) (%); ``d1`` = 100 * mean(err > 3 AND err > 0.05 * |gt|) (KITTI 2015 D1 outlier rate, %).

Semi-dense labels are therefore measured like the paper's PVM ablation (error on the labelled pixels, plus the
density). Dense network predictions have density 100 % and the numbers are the usual benchmark ones.
Empty sets give NaN (never 0, which would look perfect). :class:`MetricAccumulator` pools the integer counts
and error sums over frames, so pooled-over-pixels numbers are exact (not a mean of per-frame means).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from pvm_labeler.common.errors import InputError

BAD_THRESHOLDS: tuple[int, ...] = (1, 2, 3)
METRIC_KEYS: tuple[str, ...] = ("density", "epe", "bad1", "bad2", "bad3", "d1", "n_valid", "n_covered")


def _check(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    if pred.shape != gt.shape:
        raise InputError(f"prediction shape {pred.shape} differs from GT shape {gt.shape}")
    if pred.ndim != 2:
        raise InputError(f"expected (H, W) disparity maps, got shape {pred.shape}")
    mask = np.isfinite(gt)
    if valid is not None:
        if valid.shape != gt.shape:
            raise InputError(f"valid mask shape {valid.shape} differs from GT shape {gt.shape}")
        mask &= valid.astype(bool)
    return mask


@dataclass
class MetricAccumulator:
    """Pools exact pixel counts over frames; ``compute()`` gives the same keys as :func:`disparity_metrics`.

    Example:
        >>> acc = MetricAccumulator()
        >>> for pred, gt in frames:
        ...     acc.update(pred, gt)
        >>> acc.compute()["bad3"]
    """

    n_valid: int = 0
    n_covered: int = 0
    sum_err: float = 0.0
    n_bad1: int = 0
    n_bad2: int = 0
    n_bad3: int = 0
    n_d1: int = 0
    n_frames: int = 0

    def update(self, pred: npt.ArrayLike, gt: npt.ArrayLike, valid: npt.ArrayLike | None = None) -> dict[str, float]:
        """Add one frame; returns that frame's own metrics.

        Args:
            pred: (H, W) float disparity, NaN (or inf) = not predicted.
            gt: (H, W) float disparity, NaN/inf = unknown.
            valid: optional (H, W) bool mask further restricting the evaluated pixels (e.g. a noc mask).
        """
        pred = np.asarray(pred, dtype=np.float64)
        gt = np.asarray(gt, dtype=np.float64)
        mask = _check(pred, gt, None if valid is None else np.asarray(valid))
        covered = mask & np.isfinite(pred)
        err = np.abs(pred[covered] - gt[covered])
        frame = MetricAccumulator(
            n_valid=int(mask.sum()),
            n_covered=int(covered.sum()),
            sum_err=float(err.sum()),
            n_bad1=int((err > 1).sum()),
            n_bad2=int((err > 2).sum()),
            n_bad3=int((err > 3).sum()),
            n_d1=int(((err > 3) & (err > 0.05 * np.abs(gt[covered]))).sum()),
            n_frames=1,
        )
        self.merge(frame)
        return frame.compute()

    def merge(self, other: MetricAccumulator) -> MetricAccumulator:
        """Add another accumulator's counts (e.g. from a worker process); returns self."""
        self.n_valid += other.n_valid
        self.n_covered += other.n_covered
        self.sum_err += other.sum_err
        self.n_bad1 += other.n_bad1
        self.n_bad2 += other.n_bad2
        self.n_bad3 += other.n_bad3
        self.n_d1 += other.n_d1
        self.n_frames += other.n_frames
        return self

    def compute(self) -> dict[str, float]:
        """density/epe/bad1/bad2/bad3/d1 (NaN when undefined) plus n_valid, n_covered (as floats)."""
        nan = math.nan
        cov = self.n_covered
        return {
            "density": 100.0 * cov / self.n_valid if self.n_valid else nan,
            "epe": self.sum_err / cov if cov else nan,
            "bad1": 100.0 * self.n_bad1 / cov if cov else nan,
            "bad2": 100.0 * self.n_bad2 / cov if cov else nan,
            "bad3": 100.0 * self.n_bad3 / cov if cov else nan,
            "d1": 100.0 * self.n_d1 / cov if cov else nan,
            "n_valid": float(self.n_valid),
            "n_covered": float(cov),
        }


def disparity_metrics(pred: npt.ArrayLike, gt: npt.ArrayLike, valid: npt.ArrayLike | None = None) -> dict[str, float]:
    """Metrics of one disparity map against GT (see the module docstring for exact definitions).

    Args:
        pred: (H, W) float disparity, NaN = not predicted.
        gt: (H, W) float disparity, NaN/inf = unknown.
        valid: optional (H, W) bool, restricts the GT-valid set.

    Returns:
        dict with density (%), epe (px), bad1/bad2/bad3 (%), d1 (%), n_valid, n_covered.
    """
    return MetricAccumulator().update(pred, gt, valid)

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


# ------------------------------------------------------------------------------------------------ GT sanity check
# Plainly wrong GT (read at the wrong scale or byte order, negated, 0 for "unknown") scores as confident nonsense, so
# :func:`gt_problems` names it. Shares are of the GT-valid (finite) pixels unless said otherwise. Every real GT set in
# ../shared/data (KITTI 2012/2015, Middlebury 2001/2003/2014, FlyingThings3D) is far from each: disparities of ~1 to
# ~150 px, none below 1 px, none negative, none exactly 0.
#: Below 1 px (of the non-zero ones): an 8-bit PNG of disparity x4 read as value / 256 has all of them there; a real
#: frame's far points, where it has any, are a small part of it.
SUBPIXEL_SHARE = 0.99
#: Negative: a negated map or the right view's GT (a left-view disparity x_left - x_right is >= 0).
NEGATIVE_SHARE = 0.01
#: Exactly 0, as a share of ALL pixels: a float GT (PFM, NPY) whose unknowns are 0 instead of inf; an integer PNG's
#: 0 is read as "no GT" already, so this only fires for float GT.
ZERO_SHARE = 0.005
#: |d| outside [TINY_DISP, HUGE_DISP] (d != 0) is no disparity: floats read with the wrong byte order land there
#: (100.0 written little-endian, read big-endian, is 7.2e-41), at most IMPLAUSIBLE_SHARE of a real frame.
TINY_DISP, HUGE_DISP, IMPLAUSIBLE_SHARE = 1e-6, 1e5, 0.01


def gt_problems(gt: npt.ArrayLike, scale: float | None = None) -> list[str]:
    """What is plainly wrong with a GT map, each problem with its likely fix ([] for plausible GT).

    Args:
        gt: (H, W) float disparity as the readers decode it (NaN/inf = unknown; an integer PNG's 0 is NaN already).
        scale: the integer PNG's divisor (disparity = value / scale), None for float GT (PFM, NPY).
    """
    gt = np.asarray(gt, dtype=np.float64)
    d = gt[np.isfinite(gt)]
    if d.size == 0:
        return []
    odd = (d != 0) & ((np.abs(d) < TINY_DISP) | (np.abs(d) > HUGE_DISP))
    if odd.mean() > IMPLAUSIBLE_SHARE:  # the other checks would only echo it
        return [f"{_pct(odd.mean())} of the valid disparities are not disparities (|d| < {TINY_DISP:g} or > "
                f"{HUGE_DISP:g} px, e.g. {d[odd][0]:.2g}): a big-endian/little-endian mix-up? (a PFM's scale sign "
                "gives its byte order: negative = little-endian)"]
    problems = []
    negative = d < 0
    negated = negative.mean() > NEGATIVE_SHARE
    if negated:
        problems.append(f"{_pct(negative.mean())} of the valid disparities are negative (min {d.min():.3g} px): "
                        "negative disparities come from a negated map or the right view's GT; the left view's "
                        "disparity x_left - x_right is >= 0")
    nonzero = d[d != 0]
    if not negated and nonzero.size and (nonzero < 1).mean() >= SUBPIXEL_SHARE:
        share = "all" if (nonzero < 1).all() else _pct((nonzero < 1).mean()) + " of the"
        fix = (f"the PNG is read as value / {scale:g}: an 8-bit PNG needs --gt-scale (its disparity multiplier, "
               "e.g. 4)" if scale is not None else
               "a map in another unit (normalised by the image width?) or no disparity map")
        problems.append(f"{share} {nonzero.size:,} valid disparities are below 1 px (max {nonzero.max():.3g}): {fix}")
    width = gt.shape[-1] if gt.ndim == 2 else 0
    beyond = d >= width if width else np.zeros(d.shape, bool)
    if beyond.mean() > IMPLAUSIBLE_SHARE:  # no pixel matches beyond the image: raw integer values, another unit
        fix = (f"the integer PNG is read as value / {scale:g}: is that its multiplier (--gt-scale)?" if scale is not
               None else "raw 16-bit values never divided (KITTI's disparity is value / 256), or another unit")
        problems.append(f"{_pct(beyond.mean())} of the valid disparities are as wide as the image ({width} px) or "
                        f"wider (max {d.max():.4g}), which no pixel of the pair can match: {fix}")
    zero = float((gt == 0).mean())
    if zero > ZERO_SHARE:
        problems.append(f"{_pct(zero)} of the pixels are exactly 0: PFM unknowns should be inf (0 counts as a "
                        "disparity of 0)")
    return problems


def _pct(share: float) -> str:
    return f"{100 * share:.3g} %"

"""Densify PVM labels with planes: one least-squares plane per SLIC superpixel fills the superpixel's holes.

PVM keeps ~60 % of KITTI's pixels; the network's errors sit in the rest. Inside a superpixel (OpenCV's SLICO on
Lab, ``region_size`` px) whose labelled pixels lie on a plane d = a x + b y + c (RMS residual <= ``max_rms`` px,
at least ``MIN_LABELS`` labels making at least ``MIN_RATIO`` of it), the unlabelled pixels take the plane's
disparity. Labelled pixels are never changed. On the 15 KITTI 2015 GT frames
(``python -m pipelines.studies.hole_targets``,
evaluation only) such fills are right more often than the shipped network on the same pixels, at every distance
from the labels, yet 600 steps of training on densified labels left KITTI 2015 unchanged (RESULTS.md).

    pvm-label densify SHARD_DIR OUT [--region-size 40] [--max-rms 0.6] [--fill-confidence 0.5]

rewrites a shard directory with both views densified (left on the left image, right on the right image) and the
filled pixels' confidence set to ``fill_confidence`` (what a confidence-weighted L_P gives them), the right view's
in ``confidence_right`` (1 on PVM's right labels).

    pvm-label densify SHARD_DIR OUT --method sgm [--fill-confidence 0.3] [--views left|both]

fills every hole of the left view instead with the labeler's own matcher cleaned up: dense full-resolution SGM
(holes along the row filled, ``pvm_labeler.dense``) through the colour-weighted median (``pvm_labeler.refine``). On
the 15 KITTI 2015 GT frames that map is right more often than the shipped network inside PVM's holes (RESULTS.md).
With ``--views both`` the right view's holes get the same treatment (the labeler's right-view SGM from the same cost
volume, guided by the right image) and the shards gain ``confidence_right`` (1 on PVM's right labels,
``fill_confidence`` on the fills), the weight of the trainer's flip-swapped samples; ``left`` (the default, what version
11 trained on; version 12 trained on ``both``) leaves the right view's PVM labels as they are.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from pvm_labeler.shards.fills import add_fills, right_confidence

MIN_LABELS = 10
MIN_RATIO = 0.2
REGION_SIZE = 40
MAX_RMS = 0.6
FILL_CONFIDENCE = 0.5
METHODS = ("planes", "sgm")
VIEWS = ("left", "both")


def fill_planes(segments: npt.NDArray[np.int32], label: npt.NDArray[np.float32], max_rms: float,
                min_labels: int = MIN_LABELS, min_ratio: float = MIN_RATIO) -> npt.NDArray[np.float32]:
    """(H, W) float32: per segment id of ``segments`` (H, W) int, the least-squares plane of its labelled pixels
    (``label`` (H, W) float32, finite) evaluated at its UNLABELLED pixels, where the segment has enough labels and
    the fit's RMS residual is <= ``max_rms``; NaN elsewhere (labelled pixels included: this is what is added)."""
    h, w = label.shape
    out = np.full(h * w, np.nan, np.float32)
    ys, xs = np.divmod(np.arange(h * w), w)
    flat_label = label.ravel()
    order = np.argsort(segments, axis=None, kind="stable")
    for idx in np.split(order, np.flatnonzero(np.diff(segments.ravel()[order])) + 1):
        d = flat_label[idx]
        known = np.isfinite(d)
        n_known = int(known.sum())
        if n_known < max(min_labels, min_ratio * idx.size) or n_known == idx.size:
            continue
        design = np.stack([xs[idx], ys[idx], np.ones(idx.size)], axis=1).astype(np.float64)
        coef = np.linalg.lstsq(design[known], d[known].astype(np.float64), rcond=None)[0]
        rms = np.sqrt(np.mean((design[known] @ coef - d[known]) ** 2))
        if rms <= max_rms:
            out[idx[~known]] = design[~known] @ coef
    return out.reshape(h, w)


def plane_fill(image: npt.NDArray[np.uint8], label: npt.NDArray[np.float32], region_size: int = REGION_SIZE,
               max_rms: float = MAX_RMS) -> npt.NDArray[np.float32]:
    """:func:`fill_planes` over the SLIC superpixels of ``image`` (H, W, 3) uint8 RGB: the fills only, NaN elsewhere."""
    import cv2

    slic = cv2.ximgproc.createSuperpixelSLIC(cv2.cvtColor(image, cv2.COLOR_RGB2Lab), cv2.ximgproc.SLICO,
                                             region_size)
    slic.iterate(10)
    return fill_planes(slic.getLabels(), label, max_rms)


def densify_view(image: npt.NDArray[np.uint8], label: npt.NDArray[np.float32], confidence: npt.NDArray[np.float32],
                 region_size: int, max_rms: float, fill_confidence: float
                 ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], int]:
    """One view: (label with the plane fills added, confidence with ``fill_confidence`` there, pixels filled)."""
    return add_fills(label, confidence, plane_fill(image, label, region_size, max_rms), fill_confidence)


def sgm_fill(left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8], cfg: Any) -> npt.NDArray[np.float32]:
    """(H, W) float32 dense left-view SGM of an (H, W, 3) uint8 pair (``cfg``: a LabelerConfig; its search range),
    holes filled along the row, through the colour-weighted median guided by the left image."""
    from pvm_labeler.dense import dense_sgm
    from pvm_labeler.refine import weighted_median

    return weighted_median(dense_sgm(left, right, cfg, cfg.max_disp)[0], left)


def sgm_fills_both(left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8], cfg: Any
                   ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """(left-view :func:`sgm_fill`, the same for the right view), (H, W) float32, from one SGM cost volume
    (:func:`pvm_labeler.dense.sgm_views`). The right view is the left view's recipe mirrored: its holes fill
    along the row with ties going right (the mirror of ``fill_rows_nearest``'s left), and the median follows the
    right image; this equals :func:`sgm_fill` of the mirrored, swapped pair, mirrored back, up to a sub-pixel rounding
    on a handful of pixels (the two cost-volume indexings; tested)."""
    from pvm_labeler.dense import fill_rows_nearest, sgm_views
    from pvm_labeler.refine import weighted_median

    disp_l, disp_r = sgm_views(left, right, cfg, cfg.max_disp)
    mirrored_fill = fill_rows_nearest(np.ascontiguousarray(disp_r[:, ::-1]))[:, ::-1]
    return weighted_median(fill_rows_nearest(disp_l), left), weighted_median(mirrored_fill, right)


def densify(src: Path | str, out: Path | str, region_size: int = REGION_SIZE, max_rms: float = MAX_RMS,
            fill_confidence: float = FILL_CONFIDENCE, progress: bool = False, method: str = "planes",
            views: str = "left") -> Path:
    """Rewrite the shard directory ``src`` into ``out`` with both views' labels densified by :func:`plane_fill`
    (``method`` "planes"), or by :func:`sgm_fill` ("sgm", the matcher's settings from the shards' labeler config):
    the left view's, and with ``views`` "both" the right view's too (:func:`sgm_fills_both`, its weights in
    ``confidence_right``). ``progress``: a bar over the pairs on a terminal.

    Raises:
        ValueError: an unknown method or views, ``region_size`` < 4, ``max_rms`` <= 0 or ``fill_confidence``
            outside (0, 1].
    """
    from pvm_labeler.config import LabelerConfig
    from pvm_labeler.shards import read_index, rewrite

    if method not in METHODS:
        raise ValueError(f"densify: method must be one of {METHODS}, got {method!r}")
    if views not in VIEWS:
        raise ValueError(f"densify: views must be one of {VIEWS}, got {views!r}")
    if region_size < 4 or max_rms <= 0 or not 0 < fill_confidence <= 1:
        raise ValueError(f"densify: need region_size >= 4, max_rms > 0 and 0 < fill_confidence <= 1, got "
                         f"{region_size}, {max_rms}, {fill_confidence}")
    if method == "sgm":
        cfg = LabelerConfig.from_dict(read_index(src).config)

        def transform_sgm(sample: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
            if views == "left":
                fill_l, fill_r = sgm_fill(sample.left, sample.right, cfg), None
            else:
                fill_l, fill_r = sgm_fills_both(sample.left, sample.right, cfg)
            label, conf, n_left = add_fills(sample.label, sample.confidence, fill_l, fill_confidence)
            arrays = {"label": label, "confidence": conf.astype(np.float16)}
            if fill_r is None:
                return arrays, {"densify_filled_left": n_left}
            label_right, conf_right, n_right = add_fills(sample.label_right, right_confidence(sample.label_right),
                                                         fill_r, fill_confidence)
            return ({**arrays, "label_right": label_right, "confidence_right": conf_right.astype(np.float16)},
                    {"densify_filled_left": n_left, "densify_filled_right": n_right})

        settings = {"method": "sgm", "filter": "wmedian", "fill_confidence": fill_confidence, "views": views}
        return rewrite(src, out, transform=transform_sgm, extra={"densified_from": str(src), "densify": settings},
                       progress=progress)

    def transform(sample: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        label, conf_left, n_left = densify_view(sample.left, sample.label, sample.confidence, region_size, max_rms,
                                                fill_confidence)
        label_right, conf_right, n_right = densify_view(sample.right, sample.label_right,
                                                        right_confidence(sample.label_right), region_size, max_rms,
                                                        fill_confidence)
        return ({"label": label, "label_right": label_right, "confidence": conf_left.astype(np.float16),
                 "confidence_right": conf_right.astype(np.float16)},
                {"densify_filled_left": n_left, "densify_filled_right": n_right})

    settings = {"method": "planes", "region_size": region_size, "max_rms": max_rms, "min_labels": MIN_LABELS,
                "min_ratio": MIN_RATIO, "fill_confidence": fill_confidence}
    return rewrite(src, out, transform=transform, extra={"densified_from": str(src), "densify": settings},
                   progress=progress)

"""GT shards without a labeling pass (``pvm-label pack-gt``, ``pvm-label run --labels none``).

The supervised rows train on ground truth (``optstereo-train --supervision gt``); they need the images and GT in
shards, not PVM labels. This "labeler" leaves every label empty, so packing a dataset costs its I/O only.
"""

from __future__ import annotations

import numpy as np

from pvm_labeler.common.datasets import PairRef
from pvm_labeler.common.errors import InputError
from pvm_labeler.config import LabelerConfig
from pvm_labeler.multiscale import LabelResult

#: ``JobSpec.label_fn`` of a GT-only pack.
PACK_GT_LABELER = "pvm_labeler.packgt:no_labels"


def no_labels(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, frame_id: str) -> LabelResult:
    """label_pair's signature, no labels: label/label_right NaN, confidence 0, (H, W) of ``left``."""
    shape = left.shape[:2]
    empty = np.full(shape, np.nan, np.float32)
    return LabelResult(label=empty, label_right=empty.copy(), confidence=np.zeros(shape, np.float32),
                       eps=np.zeros(cfg.k), factors=np.ones(cfg.k), timings={})


def require_gt(refs: list[PairRef]) -> None:
    """Raise InputError naming the pairs without GT (a GT pack of them would hold nothing to train on)."""
    missing = [r for r in refs if r.gt is None]
    if missing:
        names = ", ".join(f"{r.frame_id} ({r.left})" for r in missing[:5])
        raise InputError(f"pack-gt (run --labels none) packs ground truth, but {len(missing)} of {len(refs)} pairs "
                         f"have none: {names}{' ...' if len(missing) > 5 else ''} (a folder dataset reads "
                         "its GT from --gt, default ROOT/gt)")

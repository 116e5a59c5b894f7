"""Hole fills of shard labels: one rule for every source of fills (dense SGM, planes, a teacher network).

Both the labeler's ``densify`` and optstereo's ``distill`` write fills through these two functions, so a filled
pixel means the same thing whoever filled it: PVM's labels never change, a fill gets one stated confidence.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


def add_fills(label: npt.NDArray[np.float32], confidence: npt.NDArray[np.float32], fills: npt.NDArray[np.float32],
              fill_confidence: float) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], int]:
    """(label with ``fills`` in its holes, confidence with ``fill_confidence`` there, pixels filled); (H, W) float32.

    Labelled pixels never change. Non-finite and non-positive fills (a plane extrapolated past the horizon, a
    matcher's invalid value) are no disparity: their holes stay empty.
    """
    filled = ~np.isfinite(label) & np.isfinite(fills) & (fills > 0)
    dense = np.where(filled, fills, label).astype(np.float32)
    return dense, np.where(filled, np.float32(fill_confidence), confidence).astype(np.float32), int(filled.sum())


def right_confidence(label_right: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """(H, W) float32: 1 on PVM's right-view labels, 0 in its holes. PVM keeps no right-view confidence; 1 is the
    weight the trainer gave a flip-swapped sample before ``confidence_right`` existed, so PVM's labels keep it."""
    return np.isfinite(label_right).astype(np.float32)

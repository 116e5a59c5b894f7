"""pipelines/studies/hole_targets.py: multi-scale predictions and the counts, on hand-made maps."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.studies.error_regions import REGIONS
from pipelines.studies.hole_targets import count_targets, scale_predictions, targets_table

N = np.nan


def test_scale_predictions_resize_and_rescale() -> None:
    """A stub matcher answering width / 10 px at every pixel: every scale maps back to the same full-size value."""
    left = np.zeros((20, 50, 3), np.uint8)
    calls: list[tuple[int, int]] = []

    def stub(lft: np.ndarray, rgt: np.ndarray) -> np.ndarray:
        calls.append(lft.shape[:2])
        return np.full(lft.shape[:2], lft.shape[1] / 10, np.float32)

    preds = scale_predictions(stub, left, left, scales=(1.0, 0.8, 0.5))
    assert calls == [(20, 50), (16, 40), (10, 25)]
    assert preds.shape == (3, 20, 50) and preds.dtype == np.float32
    np.testing.assert_allclose(preds, 5.0, rtol=1e-6)


def test_count_targets_and_table_by_hand() -> None:
    gt = np.array([[10, 10, 10, 10]], np.float32)
    pred = np.array([[10, 20, 10, 20]], np.float32)  # bad at columns 1 and 3
    target = np.array([[N, 10, 20, 20]], np.float32)  # covers 1-3; bad at 2 and 3
    masks = {region: np.zeros((1, 4), bool) for region in REGIONS}
    masks["labelled"][0, :2] = True
    masks["unlabelled, noc, > 10"][0, 2:] = True
    counts = count_targets(masks, gt, pred, target)
    assert counts["labelled"] == {"n": 2, "covered": 1, "bad_target": 0, "bad_net": 1}
    assert counts["unlabelled, noc, > 10"] == {"n": 2, "covered": 2, "bad_target": 2, "bad_net": 1}
    md = targets_table(counts)
    assert "| labelled | 50.0 | 0.0 | 100.0 |" in md and "| unlabelled, noc, > 10 | 100.0 | 100.0 | 50.0 |" in md
    assert "| unlabelled, occ | - | - | - |" in md


def test_picture_names_an_unknown_frame(shared_data, tmp_path) -> None:
    from pipelines.studies.hole_targets import picture

    with pytest.raises(ValueError, match="not a KITTI 2015 GT frame.*000000_10"):
        picture("nope_10", tmp_path)


def test_plane_fills_are_what_densify_adds() -> None:
    """A constant image and a plane label with a hole: the fills are the hole's plane values, NaN elsewhere."""
    from pipelines.studies.hole_targets import plane_fills

    ys, xs = np.mgrid[0:24, 0:32]
    plane = (12 + 0.3 * xs - 0.1 * ys).astype(np.float32)
    label = plane.copy()
    label[8:12, 10:14] = np.nan
    fills = plane_fills(np.full((24, 32, 3), 90, np.uint8), label, region_size=8, max_rms=0.1)
    np.testing.assert_allclose(fills[8:12, 10:14], plane[8:12, 10:14], atol=1e-3)
    assert np.isfinite(fills).sum() == 16

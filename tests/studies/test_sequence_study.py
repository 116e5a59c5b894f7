"""The sequence study's score against a drive's PVM labels (pipelines/studies/sequence_study.py), by hand."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.studies.sequence_study import against_labels


def test_against_labels_pools_the_labelled_pixels_of_every_frame() -> None:
    nan = np.nan
    disps = [np.array([[1.0, 5.0, 9.0]], np.float32), np.array([[0.0, 0.0]], np.float32)]
    labels = [np.array([[1.0, 1.0, nan]], np.float32), np.array([[4.0, 0.5]], np.float32)]
    # errors on labelled pixels: 0, 4 (frame 1); 4, 0.5 (frame 2) -> 2 of 4 over 3 px, mean 8.5 / 4
    got = against_labels(disps, labels)
    assert got["labels_bad3"] == pytest.approx(50.0) and got["labels_epe"] == pytest.approx(2.125)
    assert got["labels_pixels"] == 4

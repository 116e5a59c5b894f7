"""The fusion probe's disagreement shares (pipelines/studies/fusion_bound.py), against hand-counted pixels."""

from __future__ import annotations

import numpy as np

from pipelines.studies.fusion_bound import disagreement, summary


def test_disagreement_counts_labelled_pixels_off_by_more_than_each_delta() -> None:
    """8 pixels: 2 unlabelled (NaN, 0) whose huge gaps must not count; of the 6 labelled, gaps 0, 0.7, 2, 3, 3.5,
    10 px: > 0.5 px: 5, > 1 px: 4, > 3 px: 2 (a gap of exactly 3 is not over), each over all 8 pixels."""
    label = np.array([[np.nan, 0, 10, 10], [10, 10, 10, 10]], np.float32)
    disp = np.array([[99, 99, 10, 10.7], [12, 13, 13.5, 20]], np.float32)
    got = disagreement(disp, label)
    assert got == {"density": 6 / 8, "off_0.5": 5 / 8, "off_1": 4 / 8, "off_3": 2 / 8}


def test_summary_is_the_frame_mean_per_set_in_points() -> None:
    rows = {"a/1": {"density": 1.0, "off_3": 0.01}, "a/2": {"density": 1.0, "off_3": 0.03},
            "b/1": {"density": 0.5, "off_3": 0.5}}
    got = summary(rows)
    assert got.keys() == {"a", "b"}
    assert abs(got["a"]["off_3"] - 2.0) < 1e-9 and abs(got["b"]["off_3"] - 50.0) < 1e-9

"""The colour-weighted median (pvm_labeler.refine): against the pixel-by-pixel reference, and on hand-made edges."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import two_regions
from naive import naive_weighted_median

from pvm_labeler.refine import MedianParams, edge_pixels, weighted_median


@pytest.mark.parametrize("radius,sigma,min_range", [(1, 10.0, 0.0), (2, 25.5, 1.0), (3, 60.0, 0.5)])
def test_matches_reference(radius: int, sigma: float, min_range: float) -> None:
    rng = np.random.default_rng(radius)
    image = rng.integers(0, 256, (13, 17, 3)).astype(np.uint8)
    disp = (rng.random((13, 17)) * 30).astype(np.float32)
    disp[rng.random((13, 17)) < 0.1] = np.nan
    disp[:3, :3] = np.nan  # an all-NaN window at the corner for radius 1 stays NaN
    got = weighted_median(disp, image, MedianParams(radius, sigma, min_range))
    want = naive_weighted_median(disp, image, radius, sigma, min_range)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    # float32 accumulation of the weights may tip a near-tie; allow that on a handful of pixels
    assert np.mean(np.abs(np.nan_to_num(got - want)) > 1e-6) < 0.02


def test_blurred_edge_snaps_to_the_colour_edge() -> None:
    image, truth = two_regions()
    blurred = truth.copy()
    blurred[:, 13:17] = np.linspace(20, 5, 4, dtype=np.float32)  # a 4-px ramp across the edge at column 15
    out = weighted_median(blurred, image, MedianParams(radius=5, sigma=20.0))
    np.testing.assert_array_equal(out, truth)


def test_flat_and_sharp_maps_are_kept() -> None:
    image, truth = two_regions()
    np.testing.assert_array_equal(weighted_median(truth, image), truth)
    flat = np.full((10, 12), 7.25, np.float32)
    np.testing.assert_array_equal(weighted_median(flat, np.zeros((10, 12, 3), np.uint8)), flat)


def test_every_output_is_a_window_value_and_holes_are_filled() -> None:
    image, truth = two_regions()
    holes = truth.copy()
    holes[5:8, 3:6] = np.nan
    out = weighted_median(holes, image, MedianParams(radius=3))
    assert np.isfinite(out).all()
    assert set(np.unique(out)) <= {20.0, 5.0}


def test_edge_pixels_is_the_window_range() -> None:
    disp = np.zeros((9, 9), np.float32)
    disp[4, 4] = 2.0
    mask = edge_pixels(disp, radius=1, min_range=1.0)
    expected = np.zeros((9, 9), bool)
    expected[3:6, 3:6] = True
    np.testing.assert_array_equal(mask, expected)
    assert not edge_pixels(disp, radius=1, min_range=2.0).any()


@pytest.mark.parametrize("kwargs", [{"radius": 0}, {"sigma": 0.0}, {"min_range": -1.0}])
def test_bad_params_are_refused(kwargs: dict) -> None:
    with pytest.raises(ValueError, match="weighted median"):
        MedianParams(**kwargs)


def test_shape_mismatch_is_refused() -> None:
    with pytest.raises(ValueError, match="do not match"):
        weighted_median(np.zeros((4, 5), np.float32), np.zeros((4, 6, 3), np.uint8))

"""The weighted median in torch (optstereo.inference.refine_torch, the post-filter on a GPU): against the pixel-by-pixel
reference and the numba kernel, on hand-made edges, and through ``apply_refine``'s device dispatch."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import two_regions
from naive import naive_weighted_median

from optstereo.inference.engine import apply_refine
from optstereo.inference.refine_torch import weighted_median_torch
from pvm_labeler.refine import MedianParams, weighted_median


def noisy_scene(seed: int, height: int = 29, width: int = 41) -> tuple[np.ndarray, np.ndarray]:
    """Random colours and disparities with NaN holes, an all-NaN corner and a blurred step (every branch)."""
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (height, width, 3)).astype(np.uint8)
    disp = (rng.random((height, width)) * 30).astype(np.float32)
    disp[:, width // 2:] += 25.0
    disp[rng.random((height, width)) < 0.1] = np.nan
    disp[:3, :3] = np.nan
    return image, disp


@pytest.mark.parametrize("radius,sigma,min_range", [(1, 10.0, 0.0), (2, 25.5, 1.0), (5, 51.0, 1.0)])
def test_matches_reference_and_kernel(radius: int, sigma: float, min_range: float) -> None:
    image, disp = noisy_scene(radius)
    params = MedianParams(radius, sigma, min_range)
    got = weighted_median_torch(disp, image, params)
    want = naive_weighted_median(disp, image, radius, sigma, min_range)
    kernel = weighted_median(disp, image, params)
    for other in (want, kernel):
        np.testing.assert_array_equal(np.isnan(got), np.isnan(other))
        # float32 summation order (tree sum here, scan there) may tip a near-tie on a handful of pixels
        assert np.mean(np.abs(np.nan_to_num(got - other)) > 1e-6) < 0.01


def test_chunks_do_not_change_the_result() -> None:
    image, disp = noisy_scene(7)
    np.testing.assert_array_equal(weighted_median_torch(disp, image, chunk_pixels=13),
                                  weighted_median_torch(disp, image))


def test_blurred_edge_snaps_and_sharp_maps_are_kept() -> None:
    image, truth = two_regions()
    blurred = truth.copy()
    blurred[:, 13:17] = np.linspace(20, 5, 4, dtype=np.float32)  # a 4-px ramp across the colour edge at column 15
    np.testing.assert_array_equal(weighted_median_torch(blurred, image, MedianParams(radius=5, sigma=20.0)), truth)
    np.testing.assert_array_equal(weighted_median_torch(truth, image), truth)  # nothing to do: returned as is
    holes = truth.copy()
    holes[5:8, 3:6] = np.nan
    out = weighted_median_torch(holes, image, MedianParams(radius=3))
    assert np.isfinite(out).all() and set(np.unique(out)) <= {20.0, 5.0}  # holes filled with window values


def test_hand_computed_window() -> None:
    """One 3x3 window around (1, 1); weight exp(-d^2 / 100) for colour distance d (sigma^2 = 50): 1 at d = 0,
    exp(-1) = 0.368 at d = 10."""
    disp = np.array([[1, 1, 1], [9, 9, 2], [2, 2, 2]], np.float32)
    params = MedianParams(radius=1, sigma=float(np.sqrt(50.0)), min_range=0.0)
    image = np.zeros((3, 3, 3), np.uint8)
    image[0, :, 0] = 10  # the 1s look unlike the centre: sorted 1 (3 x 0.368), 2 (4 x 1), 9 (2 x 1);
    # total 7.10, half 3.55: the cumulative weight crosses it at 2
    assert weighted_median_torch(disp, image, params)[1, 1] == 2.0
    image = np.full((3, 3, 3), 10, np.uint8)
    image[0, :, 0] = 0
    image[1, 1, 0] = 0  # now the 1s share the centre's colour: 1 (3 x 1), 2 (4 x 0.368), 9 (1 + 0.368);
    # total 5.84, half 2.92: crossed within the 1s
    assert weighted_median_torch(disp, image, params)[1, 1] == 1.0


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="do not match"):
        weighted_median_torch(np.zeros((4, 5), np.float32), np.zeros((4, 6, 3), np.uint8))


def test_apply_refine_on_cpu_is_the_kernel() -> None:
    """On the CPU ``apply_refine`` keeps the numba kernel (the shipped figures' filter), bit for bit."""
    image, disp = noisy_scene(3)
    np.testing.assert_array_equal(apply_refine(disp, image, "wmedian", "cpu"), weighted_median(disp, image))
    assert apply_refine(disp, image, "none", "cpu") is disp


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_the_kernel() -> None:
    image, disp = noisy_scene(5, 120, 200)
    got = apply_refine(disp, image, "wmedian", "cuda")
    want = weighted_median(disp, image)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    assert np.mean(np.abs(np.nan_to_num(got - want)) > 1e-6) < 0.01

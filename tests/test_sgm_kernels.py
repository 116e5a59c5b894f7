"""Numba SGM kernels vs the pure-NumPy references in tests/naive.py (exact for integers, float32 rounding for WTA)."""

from __future__ import annotations

import naive
import numpy as np
import pytest
from kernel_refs import backward_sum, wta_volume

from pvm_labeler.kernels._lanes import DISPARITY_BLOCK, disparity_padding, path_lanes
from pvm_labeler.kernels.aggregate import aggregate_backward_wta, aggregate_forward
from pvm_labeler.kernels.cost import (
    census_dtype,
    census_transform,
    cost_volume,
    cost_volume_right,
    popcount32,
    popcount64,
)


def _census(img: np.ndarray, window: int) -> np.ndarray:
    out = np.empty(img.shape, dtype=census_dtype(window))
    census_transform(img, window, out)
    return out


def _cost(rng: np.random.Generator, height: int = 9, width: int = 23, n_disp: int = 7, window: int = 5):
    left = rng.integers(0, 256, (height, width), dtype=np.uint8)
    right = rng.integers(0, 256, (height, width), dtype=np.uint8)
    cl, cr = _census(left, window), _census(right, window)
    cost = np.empty((height, width, n_disp), dtype=np.uint8)
    cost_volume(cl, cr, window * window - 1, cost, n_disp, 0)
    return left, right, cl, cr, cost


class TestCensus:
    @pytest.mark.parametrize("window", [3, 5, 7])
    def test_feature(self, rng, window):
        img = rng.integers(0, 256, (11, 17), dtype=np.uint8)
        np.testing.assert_array_equal(_census(img, window).astype(np.uint64), naive.naive_census(img, window))

    @pytest.mark.parametrize("shape", [(7, 7), (5, 9), (9, 5), (3, 40)])
    def test_feature_small_images_all_border(self, rng, shape):
        # every column is a border column when the image is as narrow as the window (the row-wise kernel has
        # separate loops for the interior and the two borders)
        for window in (3, 5, 7):
            if min(shape) < window:
                continue
            img = rng.integers(0, 256, shape, dtype=np.uint8)
            np.testing.assert_array_equal(_census(img, window).astype(np.uint64), naive.naive_census(img, window))

    def test_hand_computed(self):
        # 3x3 around the centre 5, neighbours in raster order 1 9 2 8 3 7 4 6 -> darker ones give bits 10101010
        img = np.array([[1, 9, 2], [8, 5, 3], [7, 4, 6]], dtype=np.uint8)
        assert int(_census(img, 3)[1, 1]) == 0b10101010

    def test_popcount(self):
        for v in [0, 1, 0xFF, 0x8000000000000001, 0xFFFFFFFFFFFFFFFF, 0x123456789ABCDEF]:
            assert int(popcount64(np.uint64(v))) == bin(v).count("1")
            assert int(popcount32(np.uint32(v & 0xFFFFFFFF))) == bin(v & 0xFFFFFFFF).count("1")


class TestCostVolume:
    @pytest.mark.parametrize("window", [3, 5, 7])
    def test_feature(self, rng, window):
        _, _, cl, cr, cost = _cost(rng, window=window)
        c_max = window * window - 1
        np.testing.assert_array_equal(cost, naive.naive_cost_volume(cl, cr, cost.shape[2], c_max))
        # edge columns x < d carry the invalid cost
        assert cost[:, 0, 1:].min() == c_max and cost[:, 3, 4:].min() == c_max

    @pytest.mark.parametrize("window", [3, 5, 7])
    def test_direct_right_equals_reindex(self, rng, window):
        # the matcher computes C_r from the shared census codes; it must be the re-indexed left volume, byte for byte
        *_, cl, cr, cost = _cost(rng, width=29, n_disp=11, window=window)
        direct = np.empty_like(cost)
        cost_volume_right(cl, cr, window * window - 1, direct, cost.shape[2], 0)
        np.testing.assert_array_equal(direct, naive.naive_reindex_right(cost, window * window - 1))


class TestAggregate:
    @pytest.mark.parametrize("diag", [True, False])
    @pytest.mark.parametrize("adaptive", [False, True])
    @pytest.mark.parametrize("p2", [60, 223, 224, 400])  # uint8 lanes up to C_max + P1 + P2 = 255, uint16 beyond
    def test_feature(self, rng, diag, adaptive, p2):
        left, _, _, _, cost = _cost(rng, height=8, width=19, n_disp=6)
        p1 = 8
        lanes = path_lanes(24, p1, p2)
        assert lanes[0] == (np.uint8 if p2 <= 223 else np.uint16)
        grey = left if adaptive else None
        fwd_dirs = naive.FORWARD_PATHS_8 if diag else naive.FORWARD_PATHS_4
        bwd_dirs = naive.BACKWARD_PATHS_8 if diag else naive.BACKWARD_PATHS_4
        s = np.empty(cost.shape, dtype=np.uint16)
        aggregate_forward(cost, left, p1, p2, adaptive, diag, s, *lanes)
        np.testing.assert_array_equal(s, naive.naive_aggregate(cost, fwd_dirs, p1, p2, grey))
        maps = [np.empty(left.shape, dtype=np.float32) for _ in range(3)]
        n_paths = 2 * len(fwd_dirs)
        s_fwd = s.copy()
        backward_sum(cost, left, p1, p2, adaptive, diag, s, *lanes)  # the production backward paths, S stored
        expected = naive.naive_aggregate(cost, fwd_dirs + bwd_dirs, p1, p2, grey)
        np.testing.assert_array_equal(s, expected)
        # the fused WTA, which keeps only one pixel's S, equals the reference WTA on the reference S
        aggregate_backward_wta(cost, left, p1, p2, adaptive, diag, s_fwd, False, float(n_paths * 24), cost.shape[2],
                               *maps, *lanes)
        refs = naive.naive_wta(expected, False, float(n_paths * 24))
        for got, ref in zip(maps, refs, strict=True):
            np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6)

    @pytest.mark.parametrize(("p1", "p2"), [(0, 231), (8, 223), (115, 116)])
    def test_lane_bounds(self, rng, p1, p2):
        # extreme costs (0 or C_max only) with C_max + P1 + P2 = 255, the largest the uint8 lanes allow: path
        # costs reach C_max + P2 and neighbour candidates 255; the sentinel is 255 - P1. Any wrap shows up as a
        # mismatch against the int64 reference (checked: sentinel 255 - P1 + 12 fails here).
        assert path_lanes(24, p1, p2)[0] == np.uint8
        assert path_lanes(24, p1, p2 + 1)[0] == np.uint16
        left = rng.integers(0, 256, (7, 21), dtype=np.uint8)
        cost = (rng.random((7, 21, 9)) < 0.7).astype(np.uint8) * 24
        s = np.empty(cost.shape, dtype=np.uint16)
        aggregate_forward(cost, left, p1, p2, False, True, s, *path_lanes(24, p1, p2))
        s_fwd = s.copy()
        backward_sum(cost, left, p1, p2, False, True, s, *path_lanes(24, p1, p2))
        paths = naive.FORWARD_PATHS_8 + naive.BACKWARD_PATHS_8
        expected = naive.naive_aggregate(cost, paths, p1, p2, None)
        np.testing.assert_array_equal(s, expected)
        maps = [np.empty(left.shape, dtype=np.float32) for _ in range(3)]
        aggregate_backward_wta(cost, left, p1, p2, False, True, s_fwd, False, 192.0, cost.shape[2], *maps,
                               *path_lanes(24, p1, p2))
        for got, ref in zip(maps, naive.naive_wta(expected, False, 192.0), strict=True):
            np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6)

    @pytest.mark.parametrize(("p1", "p2", "n_disp"), [(8, 64, 11), (3, 5, 33), (8, 111, 7), (0, 115, 5)])
    def test_padding_exact(self, rng, p1, p2, n_disp):
        # D rounded up to 32 with cost C_max + P2 + 1 in the extra slots must leave every real S(d), disparity, c
        # and uniqueness bit-identical (the bound proof is in _lanes.disparity_padding); (8, 111) is the largest P2
        # that pads with P1 = 8, (0, 115) with P1 = 0.
        n_pad, pad_cost = disparity_padding(24, p1, p2, n_disp)
        assert n_pad % DISPARITY_BLOCK == 0 and n_pad > n_disp and pad_cost == 24 + p2 + 1
        if p2 > 100:  # at the limit: one more and the padded L_r + P1 would not fit in uint8
            assert disparity_padding(24, p1, p2 + 1, n_disp) == (n_disp, 0)
        left, right, cl, cr, plain = _cost(rng, height=9, width=45, n_disp=n_disp)
        padded = np.empty((*plain.shape[:2], n_pad), dtype=np.uint8)
        cost_volume(cl, cr, 24, padded, n_disp, pad_cost)
        np.testing.assert_array_equal(padded[:, :, :n_disp], plain)
        assert (padded[:, :, n_disp:] == pad_cost).all()
        right_padded = np.empty_like(padded)
        cost_volume_right(cl, cr, 24, right_padded, n_disp, pad_cost)
        np.testing.assert_array_equal(right_padded[:, :, :n_disp], naive.naive_reindex_right(plain, 24))
        lanes = path_lanes(24, p1, p2)
        results = []
        for cost in (plain, padded):
            s = np.empty(cost.shape, dtype=np.uint16)
            aggregate_forward(cost, left, p1, p2, False, True, s, *lanes)
            maps = [np.empty(left.shape, dtype=np.float32) for _ in range(3)]
            aggregate_backward_wta(cost, left, p1, p2, False, True, s, False, 192.0, n_disp, *maps, *lanes)
            backward_sum(cost, left, p1, p2, False, True, s, *lanes)
            results.append((s[:, :, :n_disp], maps))
        np.testing.assert_array_equal(results[1][0], results[0][0])
        for got, ref in zip(results[1][1], results[0][1], strict=True):
            np.testing.assert_array_equal(got, ref)

    def test_hand_computed_path(self):
        # one row, left->right path only, D = 3, P1 = 1, P2 = 4: L(x=1) = C + min(L0[d], L0[d+-1] + 1, 0 + 4) - 0
        cost = np.array([[[0, 5, 9], [6, 6, 0]]], dtype=np.uint8)
        lr = naive.naive_path(cost, (0, 1), 1, 4)
        np.testing.assert_array_equal(lr[0, 1], [6 + 0, 6 + 1, 0 + 4])


class TestWTA:
    @pytest.mark.parametrize("right_view", [False, True])
    def test_feature(self, rng, right_view):
        s = rng.integers(0, 300, (5, 13, 9), dtype=np.uint16)
        s[0, 4] = 7  # flat: not unique -> NaN
        s[1, 5] = [9, 3, 3, 8, 8, 8, 8, 8, 8]  # tie with the neighbour only: smallest d, valid
        maps = [np.empty((5, 13), dtype=np.float32) for _ in range(3)]
        wta_volume(s, right_view, 800.0, *maps)
        for got, ref in zip(maps, naive.naive_wta(s, right_view, 800.0), strict=True):
            np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6)
        assert np.isnan(maps[0][0, 4]) and maps[1][0, 4] == 0.0 and maps[2][0, 4] == 0.0
        assert maps[0][1, 5] == pytest.approx(1 + (9 - 3) / (2 * (9 - 6 + 3)))

    @pytest.mark.parametrize("n_disp", [17, 40, 64])
    def test_long_vectors(self, rng, n_disp):
        # D >= 16: d* is found block by block (16 at a time); minima in every block, at block edges, and ties
        # between blocks (the smallest d wins, the tie is not unique -> NaN) must match the reference
        s = rng.integers(50, 300, (6, n_disp + 4, n_disp), dtype=np.uint16)
        for x, d in enumerate(range(0, n_disp, 3)):
            s[0, min(x + n_disp // 2, n_disp + 3), d] = 10  # a single minimum at every third d
        s[1, -1, [15, 16]] = 5  # straddles the first block edge: neighbours, smallest d, valid
        s[2, -1, [3, n_disp - 1]] = 5  # distant tie: NaN
        maps = [np.empty(s.shape[:2], dtype=np.float32) for _ in range(3)]
        wta_volume(s, False, 800.0, *maps)
        for got, ref in zip(maps, naive.naive_wta(s, False, 800.0), strict=True):
            np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6)
        assert np.floor(maps[0][1, -1]) == 15 and np.isnan(maps[0][2, -1])

    def test_hand_computed(self):
        # S = [10, 4, 6, 20, 30]: d* = 1, offset = (10 - 6) / (2 (10 - 8 + 6)) = 0.25, second best (d >= 3) = 20
        s = np.array([[[10, 4, 6, 20, 30]] * 2], dtype=np.uint16)
        maps = [np.empty((1, 2), dtype=np.float32) for _ in range(3)]
        wta_volume(s, False, 16.0, *maps)
        assert np.isnan(maps[0][0, 0])  # x = 0 cannot have d = 1
        assert maps[0][0, 1] == pytest.approx(1.25)
        assert maps[1][0, 1] == pytest.approx(1 - 4 / 16)
        assert maps[2][0, 1] == pytest.approx(1 - 4 / 20)

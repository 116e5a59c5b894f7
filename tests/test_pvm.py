"""label_pair end to end on synthetic scenes: shift recovery, occlusion band, textureless region, reproducibility,
pyramid geometry and input validation."""

from __future__ import annotations

import dataclasses
import zlib

import cv2
import numpy as np
import pytest

from pvm_labeler.common.errors import ConfigError, InputError
from pvm_labeler.config import LabelerConfig
from pvm_labeler.multiscale import LabelResult, draw_eps, label_pair, scale_geometry

CFG = LabelerConfig(k=4, max_disp=32)


def _texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Band-limited random texture (H, W) float32 in [0, 255]: a sum of blurred noise octaves, so that it stays
    matchable after downsampling by up to ~5x and sub-pixel shifts by remap are meaningful."""
    out = np.zeros((height, width), np.float32)
    for sigma, weight in ((0.8, 0.6), (2.0, 1.0), (5.0, 1.0)):
        noise = rng.normal(0, 1, size=(height, width)).astype(np.float32)
        out += weight * cv2.GaussianBlur(noise, (0, 0), sigma) * sigma
    out -= out.min()
    return out * (255.0 / out.max())


def _shift(image: np.ndarray, disp: float) -> np.ndarray:
    """right(x) = left(x + disp) by cubic remap (so left(x) = right(x - disp))."""
    height, width = image.shape
    map_x = np.tile(np.arange(width, dtype=np.float32) + np.float32(disp), (height, 1))
    map_y = np.repeat(np.arange(height, dtype=np.float32)[:, None], width, axis=1)
    return cv2.remap(image, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def _u8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _interior(label: np.ndarray, disp: float, margin: int = 12) -> np.ndarray:
    return label[margin:-margin, int(np.ceil(disp)) + margin : -margin]


class TestLabelPair:
    @pytest.mark.parametrize("disp", [9.0, 9.5, 13.25])
    def test_feature_known_shift(self, rng, disp):
        base = _texture(rng, 96, 192)
        left, right = _u8(base), _u8(_shift(base, disp))
        res = label_pair(left, right, CFG, "shift")
        inner = _interior(res.label, disp)
        assert np.isfinite(inner).mean() > 0.8
        # Mean error within 0.25 px (parabola sub-pixel fits lock towards integers, worst at half pixels) and no
        # gross errors.
        err = np.abs(inner[np.isfinite(inner)] - disp)
        assert err.mean() <= 0.25 and np.mean(err <= 0.5) > 0.99, (err.mean(), np.mean(err <= 0.5))
        inner_r = _interior(res.label_right[:, ::-1], disp)  # the right view's invalid band is on the right edge
        assert np.isfinite(inner_r).mean() > 0.8
        err_r = np.abs(inner_r[np.isfinite(inner_r)] - disp)
        assert err_r.mean() <= 0.25 and np.mean(err_r <= 0.5) > 0.99

    def test_feature_occluded_band_rejected(self, rng):
        # Background at d = 6 and a foreground slab at d = 22 on columns [x0, x1) of the left view. Left columns
        # [x0 - 16, x0) are hidden in the right view behind the slab: LRDCC must reject them.
        h, w, x0, x1, d_bg, d_fg = 96, 224, 120, 180, 6, 22
        rng2 = np.random.default_rng(7)
        bg = _texture(rng, h, w + 64)
        fg = _texture(rng2, h, w + 64)
        xs = np.arange(w)
        left = np.where((xs >= x0) & (xs < x1), fg[:, :w], bg[:, :w])
        # right(x) shows the slab where x + d_fg lands in it, else the background at x + d_bg.
        slab = (xs + d_fg >= x0) & (xs + d_fg < x1)
        right = np.where(slab, fg[:, d_fg : d_fg + w], bg[:, d_bg : d_bg + w])
        res = label_pair(_u8(left), _u8(right), CFG, "occlusion", return_intermediates=True)
        rows = slice(12, h - 12)
        band = res.label[rows, x0 - (d_fg - d_bg) + 1 : x0 - 1]
        assert np.isfinite(band).mean() < 0.02
        # ...while the visible background and the slab interior keep most of their labels, with correct values.
        bg_cols = res.label[rows, 40 : x0 - 24]
        fg_cols = res.label[rows, x0 + 6 : x1 - 6]
        assert np.isfinite(bg_cols).mean() > 0.7 and np.isfinite(fg_cols).mean() > 0.7
        assert np.nanmedian(np.abs(bg_cols - d_bg)) < 0.5 and np.nanmedian(np.abs(fg_cols - d_fg)) < 0.5
        # The LR check did the rejecting: the voted (pre-LR) map still has values in part of the band.
        voted_band = res.intermediates["voted"][rows, x0 - (d_fg - d_bg) + 1 : x0 - 1]
        assert np.isfinite(voted_band).sum() > np.isfinite(band).sum()

    def test_feature_textureless_region_unlabelled(self, rng):
        disp = 8
        base = _texture(rng, 96, 224)
        base[24:72, 70:160] = 128.0  # one flat patch, present in both views
        left, right = _u8(base), _u8(_shift(base, disp))
        res = label_pair(left, right, CFG, "flat")
        flat_interior = res.label[26:70, 72:158]  # the patch minus the census half-window
        assert not np.isfinite(flat_interior).any()
        assert np.all(res.confidence[26:70, 72:158] == 0)
        assert not np.isfinite(res.label_right[26:70, 64:150]).any()  # the patch sits at x - 8 in the right view
        textured = res.label[12:-12, 180:-12]
        assert np.isfinite(textured).mean() > 0.7
        # The texture test is what rejects it: SGM propagates the surrounding disparity into the flat patch
        # consistently at every scale, so without it the vote keeps most of the patch.
        res = label_pair(left, right, dataclasses.replace(CFG, min_texture=0), "flat")
        assert np.isfinite(res.label[26:70, 72:158]).mean() > 0.5

    def test_cardinality(self, rng):
        base = _texture(rng, 80, 160)
        left = np.repeat(_u8(base)[:, :, None], 3, axis=2)
        right = np.repeat(_u8(_shift(base, 5))[:, :, None], 3, axis=2)
        res = label_pair(left, right, CFG, "card", return_intermediates=True)
        assert isinstance(res, LabelResult)
        for arr in (res.label, res.label_right, res.confidence):
            assert arr.shape == (80, 160) and arr.dtype == np.float32
        assert res.eps.shape == (4,) and res.factors.shape == (4,) and res.eps[0] == 0 and res.factors[0] == 1
        assert set(res.timings) >= {"pyramid", "sgm", "upsample", "vote", "lrcheck", "total"}
        labelled = np.isfinite(res.label)
        assert np.all((res.confidence >= 0) & (res.confidence <= 1))
        assert np.all(res.confidence[~labelled] == 0) and np.all(res.confidence[labelled] > 0)
        inter = res.intermediates
        assert inter["disp_l"].shape == (4, 80, 160) and inter["V"].dtype == np.uint8
        # Every label comes from a pixel with V = 0 (the vote) that also passed the LR check.
        assert np.all(inter["V"][labelled] == 0)
        assert label_pair(left, right, CFG, "card").intermediates is None

    def test_feature_min_confidence(self, rng):
        base = _texture(rng, 80, 160)
        left, right = _u8(base), _u8(_shift(base, 7.5))
        loose = label_pair(left, right, dataclasses.replace(CFG, min_confidence=0.0), "conf")
        strict = label_pair(left, right, dataclasses.replace(CFG, min_confidence=0.6), "conf")
        kept = np.isfinite(strict.label)
        assert 0 < kept.sum() < np.isfinite(loose.label).sum()
        assert np.all(strict.confidence[kept] >= 0.6)
        assert np.all(np.isfinite(loose.label[kept]))  # a stricter filter only removes labels
        np.testing.assert_array_equal(strict.label[kept], loose.label[kept])

    def test_feature_reproducible(self, rng):
        base = _texture(rng, 80, 160)
        left, right = _u8(base), _u8(_shift(base, 7.5))
        a = label_pair(left, right, CFG, "frame-17")
        b = label_pair(left, right, CFG, "frame-17")
        np.testing.assert_array_equal(a.label, b.label)  # NaN positions and values bit-identical
        np.testing.assert_array_equal(a.label_right, b.label_right)
        np.testing.assert_array_equal(a.confidence, b.confidence)
        np.testing.assert_array_equal(a.eps, b.eps)
        c = label_pair(left, right, CFG, "frame-18")
        assert not np.array_equal(a.eps, c.eps)

    def test_exception(self, rng):
        img = _u8(_texture(rng, 80, 160))
        with pytest.raises(InputError, match="left must be uint8, got float32"):
            label_pair(img.astype(np.float32), img, CFG, "x")
        with pytest.raises(InputError, match=r"right must be \(H, W, 3\) RGB or \(H, W\) grey uint8, got shape"):
            label_pair(img, img[:, :, None], CFG, "x")
        with pytest.raises(InputError, match="left must be a numpy array, got list"):
            label_pair(img.tolist(), img, CFG, "x")
        with pytest.raises(InputError, match=r"left/right sizes differ: \(80, 160\) vs \(80, 158\) for frame x"):
            label_pair(img, img[:, :158].copy(), CFG, "x")
        with pytest.raises(InputError, match="max_disp=192 must be smaller than the image width 160"):
            label_pair(img, img, LabelerConfig(k=2), "x")
        with pytest.raises(InputError, match=r"image 160x80 too small for k=6 and max_disp=150: scale \d"):
            label_pair(img, img, LabelerConfig(k=6, max_disp=150), "x")
        with pytest.raises(ConfigError, match="cfg must be a LabelerConfig, got dict"):
            label_pair(img, img, {"k": 2}, "x")
        with pytest.raises(ConfigError, match="label_mode must be one of"):
            label_pair(img, img, LabelerConfig(k=2, max_disp=16, label_mode="best"), "x")
        with pytest.raises(ConfigError, match="min_texture must be in"):
            label_pair(img, img, LabelerConfig(k=2, max_disp=16, min_texture=-1), "x")
        with pytest.raises(ConfigError, match="upsample must be one of"):
            label_pair(img, img, LabelerConfig(k=2, max_disp=16, upsample="cubic"), "x")


class TestPyramid:
    def test_feature_draw_eps(self):
        eps = draw_eps(3, "000046", 6)
        assert eps.shape == (6,) and eps.dtype == np.float64 and eps[0] == 0.0
        assert np.all(np.abs(eps[1:]) < 1) and len(set(eps[1:])) == 5
        # Stable across processes: the seed material is (seed, crc32(frame id)), not Python's salted hash().
        expected = np.random.default_rng([3, zlib.crc32(b"000046")]).uniform(-1, 1, 6)
        np.testing.assert_array_equal(eps[1:], expected[1:])
        assert not np.array_equal(draw_eps(3, "000047", 6), eps)
        assert not np.array_equal(draw_eps(4, "000046", 6), eps)
        with pytest.raises(ConfigError, match="k must be >= 1, got 0"):
            draw_eps(0, "x", 0)

    def test_feature_geometry(self):
        # 1242 x 375, eps = [0, 0.5, -0.25]: nominal factors 1, 2.5, 2.75.
        geo = scale_geometry(375, 1242, np.array([0.0, 0.5, -0.25]), 192)
        assert geo[0] == (375, 1242, 1.0, 192)
        h, w, f, d = geo[1]
        assert (h, w) == (150, 497) and f == pytest.approx(1242 / 497) and d == int(np.ceil(192 / (1242 / 497)))
        h, w, f, d = geo[2]
        assert (h, w) == (136, 452) and d == 70  # 192 * 452 / 1242 = 69.87 -> 70


def test_an_empty_pair_or_no_frame_id_is_named() -> None:
    """An empty image failed in OpenCV's cvtColor ("!_src.empty()"); frame_id None seeded the jitter as "None"."""
    image = np.zeros((0, 64, 3), np.uint8)
    with pytest.raises(InputError, match=r"empty image: left \(0, 64, 3\)"):
        label_pair(image, image, LabelerConfig(k=2, max_disp=16), "a")
    full = np.zeros((32, 64, 3), np.uint8)
    with pytest.raises(InputError, match="frame_id must be the pair's name"):
        label_pair(full, full, LabelerConfig(k=2, max_disp=16), None)  # type: ignore[arg-type]


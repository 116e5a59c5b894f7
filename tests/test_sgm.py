"""sgm_pair: known shifts, textureless regions, right view vs the flipped-swapped run, input validation, KITTI."""

from __future__ import annotations

import dataclasses

import cv2
import naive
import numpy as np
import pytest
from conftest import make_synthetic_pair

from pvm_labeler import sgm as sgm_module
from pvm_labeler.common.errors import InputError
from pvm_labeler.config import LabelerConfig
from pvm_labeler.sgm import SGMResult, release_workspace, sgm_pair

CFG = LabelerConfig(max_disp=16)


def _grey(img: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))


def smooth_shifted_pair(
    rng: np.random.Generator, height: int, width: int, disp: float
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth random texture T (noise blurred with sigma 1.2 px); left(x) = T(x), right(x) = T(x + disp) sampled by
    bicubic cv2.remap, so left(x) == right(x - disp) up to interpolation and uint8 rounding."""
    pad = 24
    noise = rng.normal(0.0, 1.0, (height, width + 2 * pad)).astype(np.float32)
    tex = cv2.GaussianBlur(noise, (0, 0), 1.2)
    tex = (tex - tex.min()) / (tex.max() - tex.min()) * 255.0
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)

    def sample(shift: float) -> np.ndarray:
        out = cv2.remap(tex, xs + pad + np.float32(shift), ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)

    return sample(0.0), sample(disp)


class TestSgmPair:
    def test_cardinality(self, synthetic_pair):
        left, right, _ = synthetic_pair
        res_l, res_r = sgm_pair(_grey(left), _grey(right), CFG, uniqueness=True)
        for res in (res_l, res_r):
            assert isinstance(res, SGMResult)
            for arr in (res.disp, res.conf):
                assert arr.shape == left.shape[:2] and arr.dtype == np.float32
            assert np.nanmin(res.conf) >= 0 and np.nanmax(res.conf) <= 1
        assert res_l.uniqueness is not None and res_l.uniqueness.shape == left.shape[:2]
        assert res_r.uniqueness is None  # the baselines filter the left view only
        plain_l, plain_r = sgm_pair(_grey(left), _grey(right), CFG)
        assert plain_l.uniqueness is None and plain_r.uniqueness is None  # on request only: it costs a pass over S
        for a, b in ((res_l, plain_l), (res_r, plain_r)):  # and it changes nothing else
            np.testing.assert_array_equal(a.disp, b.disp)
            np.testing.assert_array_equal(a.conf, b.conf)
        assert sgm_pair(_grey(left), _grey(right), CFG, right_view=False)[1] is None

    def test_integer_shift(self, rng):
        left, right = make_synthetic_pair(rng, 40, 96, 5)
        res_l, res_r = sgm_pair(_grey(left), _grey(right), CFG)
        # interior: away from the census window border and from the unmatched columns x < 5 (left) / x >= W - 5;
        # the parabola of pure noise textures wobbles a little around the integer
        for interior in (res_l.disp[3:-3, 8:-3], res_r.disp[3:-3, 3:-8]):
            err = np.abs(interior - 5.0)
            assert np.all(err < 0.5) and np.mean(err <= 0.25) > 0.98, (err.max(), np.mean(err <= 0.25))
        # a left pixel can never get a disparity larger than its column (x - d < 0 has no partner)
        cols = np.arange(96, dtype=np.float32)
        assert np.all(np.nan_to_num(res_l.disp, nan=0.0) <= cols[None, :] + 0.5)
        assert np.all(np.nan_to_num(res_r.disp, nan=0.0) <= (95 - cols)[None, :] + 0.5)

    @pytest.mark.parametrize("disp", [3.25, 6.5, 9.75])
    def test_subpixel_shift(self, rng, disp):
        left, right = smooth_shifted_pair(rng, 48, 128, disp)
        res_l, res_r = sgm_pair(left, right, CFG)
        # Census + parabola suffers from pixel locking (measured bias up to 0.18 px at quarter shifts, see
        # docs/sgm.md): the interior mean is within 0.25 px and >= 75 % of the pixels are within 0.25 px.
        for interior in (res_l.disp[4:-4, 16:-4], res_r.disp[4:-4, 4:-16]):
            assert abs(float(np.mean(interior)) - disp) <= 0.25
            assert np.mean(np.abs(interior - disp) <= 0.25) >= 0.75
            assert np.all(np.abs(interior - disp) < 1.0)

    def test_textureless(self, rng):
        # A flat grey band (128 plus independent +-1 sensor noise in each view) inside a textured pair: the census
        # codes there are noise, so no disparity matches well -> low c and low uniqueness compared to the texture.
        left, right = make_synthetic_pair(rng, 48, 128, 4)
        left, right = _grey(left), _grey(right)
        left[:, 40:100] = 128 + rng.integers(-1, 2, (48, 60))
        right[:, 36:96] = 128 + rng.integers(-1, 2, (48, 60))
        res_l, _ = sgm_pair(left, right, CFG, uniqueness=True)
        band = np.s_[5:-5, 55:85]
        textured = np.s_[5:-5, 12:34]
        assert np.median(res_l.conf[band]) < np.median(res_l.conf[textured]) - 0.3
        assert np.median(res_l.uniqueness[band]) < 0.5 * np.median(res_l.uniqueness[textured])

    def test_right_view_equals_flipped_swapped_run(self, rng):
        left, right = smooth_shifted_pair(rng, 40, 112, 6.3)
        left[:, 30:50] = rng.integers(0, 256, (40, 20), dtype=np.uint8)  # some clutter
        for cfg in (CFG, dataclasses.replace(CFG, paths=4), dataclasses.replace(CFG, p2_adaptive=True)):
            _, res_r = sgm_pair(left, right, cfg)
            flipped, _ = sgm_pair(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]), cfg,
                                  right_view=False)
            # the same cost volume (mirrored) and a mirror-symmetric set of paths: identical up to float rounding
            np.testing.assert_allclose(res_r.disp, flipped.disp[:, ::-1], atol=1e-5)
            np.testing.assert_allclose(res_r.conf, flipped.conf[:, ::-1], atol=1e-6)

    def test_workspace_reuse(self, rng):
        # the scratch arena is reused across calls of different sizes: results must not depend on what it held
        big_l, big_r = smooth_shifted_pair(rng, 40, 112, 4.5)
        small_l, small_r = smooth_shifted_pair(rng, 24, 64, 2.5)
        release_workspace()
        fresh_l, fresh_r = sgm_pair(small_l, small_r, CFG)
        sgm_pair(big_l, big_r, CFG)
        reused_l, reused_r = sgm_pair(small_l, small_r, CFG)
        left_only, _ = sgm_pair(small_l, small_r, CFG, right_view=False)
        for a, b in ((fresh_l, reused_l), (fresh_r, reused_r), (fresh_l, left_only)):
            np.testing.assert_array_equal(a.disp, b.disp)
            np.testing.assert_array_equal(a.conf, b.conf)
        release_workspace()

    @pytest.mark.parametrize("max_disp", [13, 45])
    def test_padded_disparities_exact(self, rng, max_disp, monkeypatch):
        # D is rounded up to 32 internally (no scalar loop remainders); with padding switched off the maps must be
        # bit-identical, both views
        assert sgm_module.disparity_padding(24, CFG.p1, CFG.p2, max_disp)[0] > max_disp  # padding is on here
        left, right = smooth_shifted_pair(rng, 30, 90, 7.5)
        padded = sgm_pair(left, right, CFG, max_disp=max_disp)
        monkeypatch.setattr(sgm_module, "disparity_padding", lambda c_max, p1, p2, n: (n, 0))
        plain = sgm_pair(left, right, CFG, max_disp=max_disp)
        for a, b in zip(padded, plain, strict=True):
            for name in ("disp", "conf", "uniqueness"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert np.nanmax(padded[0].disp) < max_disp

    def test_max_disp_override(self, rng):
        left, right = make_synthetic_pair(rng, 32, 64, 6)
        res, _ = sgm_pair(_grey(left), _grey(right), CFG, max_disp=4, right_view=False)
        assert np.nanmax(res.disp) <= 3.0  # d in [0, 4)


Z = np.zeros((20, 40), np.uint8)


class TestSgmPairExceptions:
    @pytest.mark.parametrize(
        ("left", "right", "cfg", "max_disp", "match"),
        [
            ([[0]], Z, CFG, None, "left must be a numpy array, got list"),
            (np.zeros((20, 40, 3), np.uint8), Z, CFG, None, r"ndim=3 shape=\(20, 40, 3\)"),
            (Z, np.zeros((20, 40), np.float32), CFG, None, "right must be uint8, got dtype float32"),
            (Z, np.zeros((20, 42), np.uint8), CFG, None, r"\(20, 40\) vs \(20, 42\)"),
            (Z, Z, CFG, 1, "max_disp must be an integer >= 2, got 1"),
            (Z, Z, CFG, 2.5, "max_disp must be an integer >= 2, got 2.5"),
            (Z, Z, CFG, 64, "image width 40 must be >= max_disp 64"),
            (Z, Z, dataclasses.replace(CFG, census_window=9), None, r"census_window must be one of \(3, 5, 7\), got 9"),
            (np.zeros((4, 40), np.uint8), np.zeros((4, 40), np.uint8), CFG, None, r"image size \(4, 40\) is smaller"),
            (Z, Z, dataclasses.replace(CFG, p2=20000), None, "C_max \\+ p2 < 16383"),
            (Z, Z, dataclasses.replace(CFG, p2=9000), None, "overflows the uint16 cost sum"),
        ],
    )
    def test_exception(self, left, right, cfg, max_disp, match):
        with pytest.raises(InputError, match=match):
            sgm_pair(left, right, cfg, max_disp=max_disp)

    def test_non_contiguous_is_copied(self, rng):
        left, right = make_synthetic_pair(rng, 32, 128, 4)
        a, _ = sgm_pair(_grey(left)[:, ::2], _grey(right)[:, ::2], CFG, right_view=False)
        b, _ = sgm_pair(np.ascontiguousarray(_grey(left)[:, ::2]), np.ascontiguousarray(_grey(right)[:, ::2]), CFG,
                        right_view=False)
        np.testing.assert_array_equal(a.disp, b.disp)


def _kitti(shared_data, frame: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    root = shared_data / "kitti15" / "training"
    left = cv2.imread(str(root / "image_2" / f"{frame}_10.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(root / "image_3" / f"{frame}_10.png"), cv2.IMREAD_GRAYSCALE)
    gt_path = root / "disp_noc_0" / f"{frame}_10.png"
    if not gt_path.exists():
        gt_path = root / "disp_occ_0" / f"{frame}_10.png"
    gt = cv2.imread(str(gt_path), cv2.IMREAD_UNCHANGED).astype(np.float32) / 256.0
    return left, right, gt


def _sgm_lr_counts(shared_data, frame: str) -> tuple[int, int, int]:
    """(bad-3 pixels, GT-valid pixels kept by SGM + LR, GT-valid pixels) of one frame."""
    left, right, gt = _kitti(shared_data, frame)
    res_l, res_r = sgm_pair(left, right, LabelerConfig())
    checked = naive.naive_lr_check(res_l.disp, res_r.disp, 1.0)
    valid = gt > 0
    covered = valid & np.isfinite(checked)
    bad = int(np.sum(np.abs(checked[covered] - gt[covered]) > 3.0))
    return bad, int(covered.sum()), int(valid.sum())


def test_kitti_full_res_sgm_lr(shared_data):
    """Full-res SGM + LR (1 px) on KITTI 2015 frame 000000: bad-3 < 8 % over the GT pixels it covers, density
    > 70 % (measured 4.7 % / 81 %; pooled over all 15 frames 4.74 % / 82.4 %, the issue's reference 4.97 % / 82 %)."""
    bad, covered, valid = _sgm_lr_counts(shared_data, "000000")
    assert bad / covered < 0.08 and covered / valid > 0.70, (bad / covered, covered / valid)


@pytest.mark.slow
def test_kitti_all_frames_sgm_lr(shared_data):
    """All 15 KITTI 2015 frames, pooled over pixels: bad-3 < 6 % and density > 78 % (measured 4.74 % / 82.4 %);
    per frame bad-3 < 15 % (the hardest, 000006 with disparities up to 116 px, measured 13.5 %)."""
    frames = sorted(p.name[:6] for p in (shared_data / "kitti15" / "training" / "image_2").glob("*_10.png"))
    assert len(frames) == 15
    totals = np.zeros(3, dtype=np.int64)
    for frame in frames:
        counts = _sgm_lr_counts(shared_data, frame)
        assert counts[0] / counts[1] < 0.15, (frame, counts)
        totals += counts
    bad, covered, valid = totals
    assert bad / covered < 0.06 and covered / valid > 0.78, (bad / covered, covered / valid)

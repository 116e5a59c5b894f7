"""PVStereo losses (paper Section III-C) against hand-computed values, skimage SSIM and real KITTI GT."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import make_synthetic_pair

from optstereo.training.losses import (
    PVStereoLoss,
    huber,
    photometric_error,
    reconstruction_loss,
    sequence_huber_loss,
    sequence_weights,
    smoothness_loss,
    ssim,
    warp_right_to_left,
)
from optstereo.training.sections import LossConfig

NAN = float("nan")


def _to_tensor(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float()


class TestHuber:
    def test_feature_values(self) -> None:
        x = torch.tensor([0.0, 0.5, 1.0, 3.0])
        torch.testing.assert_close(huber(x), torch.tensor([0.0, 0.125, 0.5, 2.5]))

    def test_feature_sequence_weights(self) -> None:
        w = sequence_weights(8, 0.8)
        raw = torch.tensor([0.8 ** (8 - i) for i in range(1, 9)])
        torch.testing.assert_close(w, raw / raw.sum())
        assert w[-1] == w.max() and abs(w.sum().item() - 1) < 1e-6
        torch.testing.assert_close(sequence_weights(1, 0.8), torch.tensor([1.0]))


class TestSequenceHuber:
    def test_feature_hand_computed(self) -> None:
        label = torch.tensor([[[[1.0, 2.0], [NAN, 4.0]]]])
        p1 = torch.zeros(1, 1, 2, 2)  # errors 1, 2, -, 4 -> huber 0.5, 1.5, 3.5 -> mean 5.5 / 3
        p2 = torch.nan_to_num(label, nan=7.0) + 0.5  # errors 0.5 each -> 0.125
        got = sequence_huber_loss([p1, p2], label, None, gamma=0.8)
        want = (0.8 * 5.5 / 3 + 1.0 * 0.125) / 1.8
        assert abs(got.item() - want) < 1e-6

    def test_feature_valid_mask(self) -> None:
        label = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])
        valid = torch.tensor([[[[True, False], [False, False]]]])
        got = sequence_huber_loss([torch.zeros(1, 1, 2, 2)], label, valid)
        assert abs(got.item() - 0.5) < 1e-6

    def test_gradcheck_only_labelled_pixels(self) -> None:
        label = torch.tensor([[[[1.0, NAN], [3.0, 4.0]]]])
        valid = torch.tensor([[[[True, True], [False, True]]]])
        pred = torch.zeros(1, 1, 2, 2, requires_grad=True)
        sequence_huber_loss([pred], label, valid).backward()
        assert pred.grad[0, 0, 0, 1] == 0 and pred.grad[0, 0, 1, 0] == 0  # NaN label, invalid pixel
        assert pred.grad[0, 0, 0, 0] != 0 and torch.isfinite(pred.grad).all()

    def test_feature_no_labels(self) -> None:
        pred = torch.ones(1, 1, 2, 2, requires_grad=True)
        loss = sequence_huber_loss([pred], torch.full((1, 1, 2, 2), NAN))
        loss.backward()
        assert loss.item() == 0.0 and torch.isfinite(pred.grad).all()

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="preds is empty"):
            sequence_huber_loss([], torch.zeros(1, 1, 2, 2))
        with pytest.raises(ValueError, match=r"label shape \(1, 1, 2, 3\) differs from prediction shape"):
            sequence_huber_loss([torch.zeros(1, 1, 2, 2)], torch.zeros(1, 1, 2, 3))


class TestWarp:
    def test_feature_zero_disparity_is_identity(self) -> None:
        right = torch.rand(2, 3, 5, 9) * 255
        warped, valid = warp_right_to_left(right, torch.zeros(2, 1, 5, 9))
        torch.testing.assert_close(warped, right)
        assert valid.all()

    def test_feature_integer_shift(self, rng: np.random.Generator) -> None:
        left, right = make_synthetic_pair(rng, 16, 40, 4)
        warped, valid = warp_right_to_left(_to_tensor(right), torch.full((1, 1, 16, 40), 4.0))
        assert not valid[..., :4].any() and valid[..., 4:].all()
        torch.testing.assert_close(warped[..., 4:], _to_tensor(left)[..., 4:], rtol=0, atol=1e-3)

    def test_feature_fractional_shift_on_ramp(self) -> None:
        """Linear interpolation is exact on a linear ramp: right(x) = x -> warped(x) = x - 0.25."""
        right = torch.arange(10.0).view(1, 1, 1, 10).expand(1, 3, 4, 10).contiguous()
        warped, valid = warp_right_to_left(right, torch.full((1, 1, 4, 10), 0.25))
        torch.testing.assert_close(warped[..., 1:], right[..., 1:] - 0.25)
        assert not valid[..., 0].any() and valid[..., 1:].all()

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"disp must be \(B, 1, H, W\) = \(1, 1, 4, 5\), got \(1, 4, 5\)"):
            warp_right_to_left(torch.zeros(1, 3, 4, 5), torch.zeros(1, 4, 5))


class TestSSIM:
    def test_feature_self_is_one(self) -> None:
        x = torch.rand(2, 3, 8, 9)
        torch.testing.assert_close(ssim(x, x), torch.ones(2, 3, 8, 9))

    def test_feature_matches_skimage(self) -> None:
        from skimage.metrics import structural_similarity

        g = torch.Generator().manual_seed(0)
        x = torch.rand(1, 1, 12, 14, generator=g, dtype=torch.float64)
        y = (x + 0.2 * torch.rand(1, 1, 12, 14, generator=g, dtype=torch.float64)).clamp(0, 1)
        ref = structural_similarity(
            x[0, 0].numpy(), y[0, 0].numpy(), win_size=3, data_range=1.0, use_sample_covariance=False
        )
        # skimage averages the map without the 1-pixel border that its window cannot cover.
        ours = ssim(x, y)[0, 0, 1:-1, 1:-1].mean().item()
        assert abs(ours - ref) < 1e-9
        assert ours < 0.99


class TestReconstruction:
    def test_feature_correct_vs_wrong_disparity(self, rng: np.random.Generator) -> None:
        left, right = make_synthetic_pair(rng, 24, 64, 5)
        lt, rt = _to_tensor(left), _to_tensor(right)
        good = torch.full((1, 1, 24, 64), 5.0)
        warped, _ = warp_right_to_left(rt / 255, good)
        err = photometric_error(lt / 255, warped)
        assert err[..., 1:-1, 6:-1].max() < 1e-5  # interior, away from the unmatched band's SSIM window
        at_gt = reconstruction_loss(lt, rt, good).item()
        assert at_gt < 0.01
        # Grows with the disparity error: 0.25 px < 0.5 px < whole pixels (random texture: >= 1 px is uncorrelated).
        l_q, l_h, l_far = (reconstruction_loss(lt, rt, torch.full_like(good, d)).item() for d in (5.25, 5.5, 3.0))
        assert 10 * at_gt < l_q < l_h < l_far, (at_gt, l_q, l_h, l_far)
        assert all(reconstruction_loss(lt, rt, torch.full_like(good, d)).item() > l_h for d in (4.0, 6.0, 8.0))

    def test_gradcheck(self, rng: np.random.Generator) -> None:
        left, right = make_synthetic_pair(rng, 8, 16, 2)
        disp = torch.full((1, 1, 8, 16), 2.3, requires_grad=True)
        reconstruction_loss(_to_tensor(left), _to_tensor(right), disp).backward()
        assert torch.isfinite(disp.grad).all() and disp.grad.abs().sum() > 0

    def test_feature_kitti_gt_minimises_error(self, shared_data) -> None:
        """Real data: on KITTI 2015 frame 000000 the photometric error is lowest with the GT disparity (positive
        convention, x - D); shifting it by +-3 px or using 0 is worse. GT is sparse (LiDAR), and SSIM windows
        need dense disparities, so the GT is filled by nearest neighbour and the error is read at GT pixels."""
        import cv2
        from scipy import ndimage

        root = shared_data / "kitti15" / "training"
        left = cv2.imread(str(root / "image_2" / "000000_10.png"))[:, :, ::-1]
        right = cv2.imread(str(root / "image_3" / "000000_10.png"))[:, :, ::-1]
        gt = cv2.imread(str(root / "disp_occ_0" / "000000_10.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 256
        nearest = ndimage.distance_transform_edt(gt <= 0, return_distances=False, return_indices=True)
        dense = torch.from_numpy(gt[nearest[0], nearest[1]])[None, None]
        has_gt = torch.from_numpy(gt > 0)[None, None]
        lt, rt = _to_tensor(left), _to_tensor(right)

        def err(disp: torch.Tensor) -> float:
            warped, valid = warp_right_to_left(rt / 255, disp)
            return photometric_error(lt / 255, warped)[has_gt & valid].mean().item()

        at_gt = err(dense)
        others = {"zero": err(torch.zeros_like(dense)), "+3": err(dense + 3), "-3": err((dense - 3).clamp(min=0))}
        assert all(at_gt < 0.8 * v for v in others.values()), (at_gt, others)
        l_r = reconstruction_loss(lt, rt, dense)
        assert l_r < reconstruction_loss(lt, rt, dense + 3) and l_r < reconstruction_loss(lt, rt, dense - 3)


class TestSmoothness:
    def test_feature_hand_computed(self) -> None:
        disp = torch.tensor([[[[0.0, 1.0, 3.0], [0.0, 1.0, 3.0]]]])
        image = torch.zeros(1, 3, 2, 3)
        image[..., 2] = 255.0  # an intensity edge between columns 1 and 2
        # dx D = 1, 2 per row; dy D = 0. The edge is 1 in each of the 3 channels: the paper's L1 norm over
        # channels gives weights exp(0) = 1 and exp(-3); the channel mean exp(-1).
        want = (1.0 + 2.0 * np.exp(-3.0)) / 2
        assert abs(smoothness_loss(disp, image).item() - want) < 1e-6
        want_mean = (1.0 + 2.0 * np.exp(-1.0)) / 2
        assert abs(smoothness_loss(disp, image, color_norm="mean").item() - want_mean) < 1e-6

    def test_photometric_l1_term_is_the_norm_over_channels(self) -> None:
        left = torch.zeros(1, 3, 5, 5)
        warped = left.clone()
        warped[:, 0] += 0.3
        warped[:, 2] += 0.1  # per-pixel differences 0.3, 0, 0.1: L1 norm 0.4, channel mean 0.4 / 3
        from optstereo.training.losses import ssim

        dssim = ((1.0 - ssim(left, warped)) / 2.0).clamp(0, 1).mean(dim=1, keepdim=True)
        l1 = photometric_error(left, warped, alpha=0.85) - 0.85 * dssim
        mean = photometric_error(left, warped, alpha=0.85, color_norm="mean") - 0.85 * dssim
        torch.testing.assert_close(l1, torch.full_like(l1, 0.15 * 0.4))
        torch.testing.assert_close(mean, torch.full_like(mean, 0.15 * 0.4 / 3))
        with pytest.raises(ValueError, match="color_norm"):
            photometric_error(left, warped, color_norm="max")

    def test_feature_mean_normalisation_is_scale_invariant(self) -> None:
        disp = torch.rand(1, 1, 6, 7) + 1
        image = torch.rand(1, 3, 6, 7) * 255
        a = smoothness_loss(disp, image, normalize="mean")
        b = smoothness_loss(3 * disp, image, normalize="mean")
        torch.testing.assert_close(a, b)
        torch.testing.assert_close(smoothness_loss(3 * disp, image), 3 * smoothness_loss(disp, image))

    def test_feature_second_order_hand_computed(self) -> None:
        disp = torch.tensor([[[[0.0, 1.0, 3.0, 3.0], [0.0, 1.0, 3.0, 3.0]]]])
        image = torch.zeros(1, 3, 2, 4)
        image[..., 3] = 255.0  # an intensity edge between columns 2 and 3
        # dxx D = 3 - 2 + 0 = 1 at column 1 (spans steps 0-1 and 1-2: no edge, weight 1) and 3 - 6 + 1 = -2 at
        # column 2 (spans step 2-3, the edge: weight exp(-3)); dyy D has no entries (2 rows), so it adds nothing.
        want = (1.0 + 2.0 * np.exp(-3.0)) / 2
        assert abs(smoothness_loss(disp, image, order=2).item() - want) < 1e-6

    def test_feature_second_order_is_zero_on_planes(self, rng: np.random.Generator) -> None:
        yy, xx = torch.meshgrid(torch.arange(9.0), torch.arange(13.0), indexing="ij")
        plane = (20 + 0.7 * xx - 0.4 * yy)[None, None]
        image = torch.from_numpy(rng.uniform(0, 255, (1, 3, 9, 13))).float()
        assert smoothness_loss(plane, image, order=2).item() < 1e-5
        assert smoothness_loss(plane, image, order=1).item() > 0.1  # the paper's L_S penalises every slant

    def test_feature_second_order_matches_numpy_reference(self, rng: np.random.Generator) -> None:
        disp = rng.uniform(0, 50, (2, 1, 6, 7))
        image = rng.uniform(0, 255, (2, 3, 6, 7))
        img = image / 255.0
        total = 0.0
        for axis in (3, 2):
            grad = np.abs(np.diff(img, axis=axis)).sum(axis=1, keepdims=True)
            second = np.diff(disp, n=2, axis=axis)
            n = grad.shape[axis] - 1
            weight = np.exp(-np.maximum(grad.take(range(n), axis=axis), grad.take(range(1, n + 1), axis=axis)))
            total += (np.abs(second) * weight).mean()
        got = smoothness_loss(torch.from_numpy(disp).float(), torch.from_numpy(image).float(), order=2)
        assert abs(got.item() - total) < 1e-4 * total

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="normalize must be"):
            smoothness_loss(torch.zeros(1, 1, 2, 2), torch.zeros(1, 3, 2, 2), normalize="max")
        with pytest.raises(ValueError, match="order must be one of"):
            smoothness_loss(torch.zeros(1, 1, 2, 2), torch.zeros(1, 3, 2, 2), order=3)


class TestPVStereoLoss:
    def _inputs(self, rng: np.random.Generator) -> tuple[list[torch.Tensor], torch.Tensor, ...]:
        left, right = make_synthetic_pair(rng, 16, 32, 3)
        lt, rt = _to_tensor(left), _to_tensor(right)
        preds = [(torch.full((1, 1, 16, 32), v) + torch.rand(1, 1, 16, 32)).requires_grad_() for v in (1.0, 2.0, 2.5)]
        label = torch.full((1, 1, 16, 32), 3.0)
        label[..., :3] = NAN
        return preds, lt, rt, label, torch.isfinite(label)

    def test_feature_total_is_weighted_sum(self, rng: np.random.Generator) -> None:
        preds, lt, rt, label, valid = self._inputs(rng)
        total, terms = PVStereoLoss()(preds, lt, rt, label, valid)
        assert set(terms) == {"L_P", "L_R", "L_S", "total"}
        torch.testing.assert_close(terms["L_P"], sequence_huber_loss(preds, label, valid, 0.8))
        torch.testing.assert_close(terms["L_R"], reconstruction_loss(lt, rt, preds[-1]))
        torch.testing.assert_close(terms["L_S"], smoothness_loss(preds[-1], lt))
        torch.testing.assert_close(total, terms["L_P"] + 0.1 * terms["L_R"] + 0.1 * terms["L_S"])
        assert total.requires_grad and not terms["total"].requires_grad

    def test_feature_second_order_term(self, rng: np.random.Generator) -> None:
        preds, lt, rt, label, valid = self._inputs(rng)
        _, terms = PVStereoLoss(smoothness_order=2)(preds, lt, rt, label, valid)
        torch.testing.assert_close(terms["L_S"], smoothness_loss(preds[-1], lt, order=2))

    def test_feature_supervised_mode(self, rng: np.random.Generator) -> None:
        preds, lt, rt, label, valid = self._inputs(rng)
        total, terms = PVStereoLoss(lambda_r=0.0, lambda_s=0.0)(preds, lt, rt, label, valid)
        assert terms["L_R"] == 0 and terms["L_S"] == 0
        torch.testing.assert_close(total, terms["L_P"])

    def test_feature_all_iterations(self, rng: np.random.Generator) -> None:
        preds, lt, rt, label, valid = self._inputs(rng)
        _, terms = PVStereoLoss(photometric_iters="all")(preds, lt, rt, label, valid)
        w = sequence_weights(3, 0.8)
        want = sum(wi * reconstruction_loss(lt, rt, p) for wi, p in zip(w, preds, strict=True))
        torch.testing.assert_close(terms["L_R"], want)

    def test_smoke_from_config(self) -> None:
        cfg = LossConfig(lambda_r=0.2, lambda_s=0.1)
        assert PVStereoLoss.from_config(cfg).config == cfg
        assert LossConfig.from_dict(cfg.to_dict()) == cfg

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"gamma": 0.0}, "gamma must be in"),
            ({"lambda_r": -1.0}, "lambda_r=-1.0"),
            ({"alpha": 2.0}, "alpha must be in"),
            ({"photometric_iters": "first"}, "--photometric-iters must be one of"),
            ({"smoothness_norm": "max"}, "--smoothness-norm must be one of"),
            ({"smoothness_order": 3}, "--smoothness-order must be one of"),
        ],
    )
    def test_exception(self, kwargs: dict, match: str) -> None:
        with pytest.raises(ValueError, match=match):
            PVStereoLoss(**kwargs)

    def test_exception_unknown_key(self) -> None:
        with pytest.raises(ValueError, match=r"unknown loss config keys \['beta'\]"):
            LossConfig.from_dict({"beta": 1})


def test_confidence_weighted_sequence_loss_hand_computed() -> None:
    """Weighted L_P = sum(w * huber) / sum(w) over labelled pixels: two pixels with errors 2 and 0.5."""
    from optstereo.training.losses import sequence_huber_loss

    pred = torch.tensor([[[[3.0, 1.5, 9.0]]]])
    label = torch.tensor([[[[1.0, 1.0, float("nan")]]]])
    weight = torch.tensor([[[[0.25, 0.75, 1.0]]]])
    # huber(2) = 1.5, huber(0.5) = 0.125; the NaN pixel is not used whatever its weight
    expected = (0.25 * 1.5 + 0.75 * 0.125) / (0.25 + 0.75)
    assert float(sequence_huber_loss([pred], label, weight=weight)) == pytest.approx(expected)
    unweighted = (1.5 + 0.125) / 2
    assert float(sequence_huber_loss([pred], label)) == pytest.approx(unweighted)
    assert float(sequence_huber_loss([pred], label, weight=torch.ones_like(weight))) == pytest.approx(unweighted)


def test_smoothness_of_mismatched_sizes_is_named() -> None:
    """disp (1, 1, 8, 8) with an image (1, 3, 8, 9) failed inside torch: "The size of tensor a (7) must match"."""
    with pytest.raises(ValueError, match=r"disp \(B, 1, H, W\) and image \(B, 3, H, W\) of one size, got \(1, 1, 8"):
        smoothness_loss(torch.zeros(1, 1, 8, 8), torch.zeros(1, 3, 8, 9))

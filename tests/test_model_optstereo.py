"""OptStereo end to end: registry/config, shapes, gradients, input checks, autocast, real data, overfitting."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import TINY, make_synthetic_pair, overfit_epe

from optstereo.inference.padding import InputPadder
from optstereo.models import OptStereo, build_from_config, build_model, list_models, register_model
from optstereo.models.config import ModelConfig

# Small widths for wiring tests; the paper's C = 256 is used where the test is about shapes.


def _to_tensor(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(img).permute(2, 0, 1)[None].float()


def _two_plane_pair(rng: np.random.Generator, height: int = 64, width: int = 128) -> tuple[torch.Tensor, ...]:
    """Upper half shifted by 4 px, lower half by 12 px; label NaN where a pixel has no match."""
    top = make_synthetic_pair(rng, height // 2, width, 4)
    bottom = make_synthetic_pair(rng, height // 2, width, 12)
    left = _to_tensor(np.concatenate([top[0], bottom[0]]))
    right = _to_tensor(np.concatenate([top[1], bottom[1]]))
    label = torch.full((1, 1, height, width), 12.0)
    label[..., : height // 2, :] = 4.0
    label[..., : height // 2, :4] = float("nan")
    label[..., height // 2 :, :12] = float("nan")
    return left, right, label


class TestRegistry:
    def test_smoke(self) -> None:
        assert {"optstereo", "optstereo_ss_d4", "optstereo_ms_d1", "optstereo_ms_d2", "optstereo_ms_d4"} <= set(
            list_models()
        )

    @pytest.mark.parametrize(
        ("name", "levels", "radius"),
        [
            ("optstereo", 4, 4),
            ("optstereo_ss_d4", 1, 4),
            ("optstereo_ms_d1", 4, 1),
            ("optstereo_ms_d2", 4, 2),
            ("optstereo_ms_d4", 4, 4),
        ],
    )
    def test_feature_variants(self, name: str, levels: int, radius: int) -> None:
        model = build_model(name, **TINY)
        assert model.config.name == name
        assert (model.corr_block.num_levels, model.corr_block.radius) == (levels, radius)
        assert model.config.corr_channels == levels * (2 * radius + 1)
        assert model.update_block.convzr.in_channels == 16 + 1 + levels * (2 * radius + 1)

    def test_feature_paper_defaults(self) -> None:
        model = build_model("optstereo")
        cfg = model.config
        assert (cfg.feature_dim, cfg.corr_levels, cfg.corr_radius, cfg.iters, cfg.upsampler) == (256, 4, 4, 8, "conv")
        assert model.corr_block.out_channels == 36
        assert model.feature_encoder.proj.out_channels == 256

    def test_feature_rebuild_from_config(self) -> None:
        torch.manual_seed(0)
        model = build_model("optstereo_ms_d2", iters=3, upsampler="convex", **TINY)
        saved = model.config.to_dict()
        rebuilt = build_from_config(saved)
        assert rebuilt.config == model.config
        rebuilt.load_state_dict(model.state_dict())  # same architecture, strict keys
        again = build_model(saved["name"], **{k: v for k, v in saved.items() if k != "name"})
        assert again.config == model.config

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="unknown model 'raft'"):
            build_model("raft")
        with pytest.raises(ValueError, match="unknown model config keys \\['hidden'\\]"):
            build_model("optstereo", hidden=3)
        with pytest.raises(ValueError, match="upsampler must be one of"):
            build_model("optstereo", upsampler="nearest")
        with pytest.raises(ValueError, match="stage1 must be one of"):
            build_model("optstereo", stage1="mobile")
        with pytest.raises(ValueError, match="stage2 must be one of"):
            build_model("optstereo", stage2="mobile")
        with pytest.raises(ValueError, match="corr_levels must be >= 1, got 0"):
            ModelConfig(corr_levels=0).validate()
        with pytest.raises(ValueError, match="already registered"):
            register_model("optstereo", lambda cfg: torch.nn.Identity())


class TestForward:
    def test_cardinality_paper_width(self) -> None:
        """The paper's C = 256 at a small size: N_s full-size predictions, and the test-mode pair."""
        model = build_model("optstereo", iters=3)
        left = torch.rand(1, 3, 32, 64) * 255
        with torch.no_grad():
            preds = model(left, left.flip(-1))
            low, full = model(left, left.flip(-1), test_mode=True)
        assert len(preds) == 3 and all(p.shape == (1, 1, 32, 64) for p in preds)
        assert low.shape == (1, 1, 4, 8) and full.shape == (1, 1, 32, 64)
        torch.testing.assert_close(full, preds[-1])  # test mode upsamples only the last, same value

    def test_cardinality_default_iters(self) -> None:
        model = build_model("optstereo_ss_d4", **TINY)
        with torch.no_grad():
            preds = model(torch.rand(2, 3, 16, 40) * 255, torch.rand(2, 3, 16, 40) * 255)
        assert len(preds) == 8 and preds[0].shape == (2, 1, 16, 40)

    @pytest.mark.parametrize("upsampler", ["conv", "convex"])
    def test_gradcheck_backward_reaches_every_parameter(self, upsampler: str) -> None:
        torch.manual_seed(1)
        model = build_model("optstereo", iters=3, upsampler=upsampler, **TINY)
        left = torch.rand(2, 3, 32, 64) * 255
        right = torch.rand(2, 3, 32, 64) * 255
        preds = model(left, right)
        sum(p.mean() for p in preds).backward()
        for name, param in model.named_parameters():
            assert param.grad is not None, f"{name} got no gradient"
            assert torch.isfinite(param.grad).all(), f"{name} has a non-finite gradient"
            assert param.grad.abs().sum() > 0, f"{name} has an all-zero gradient"

    @pytest.mark.parametrize("norm", ["instance", "batch"])
    def test_image_chunking_same_result(self, norm: str) -> None:
        # per-image encoder calls (the CPU default) must give the one-call outputs and gradients; batch norm is
        # never chunked (its statistics span the batch), so there the two settings are the same code path
        torch.manual_seed(2)
        model = build_model("optstereo", iters=2, norm=norm, **TINY).train()
        left = torch.rand(3, 3, 32, 64) * 255
        right = torch.rand(3, 3, 32, 64) * 255
        calls = []
        model.feature_encoder.register_forward_hook(lambda mod, inp, out: calls.append(inp[0].shape[0]))
        up_calls = []
        model.upsampler.register_forward_hook(lambda mod, inp, out: up_calls.append(inp[0].shape[0]))
        results = []
        for chunk in (0, 1, 4):
            model.image_chunk = chunk
            model.zero_grad()
            preds = model(left, right)
            sum(p.mean() for p in preds).backward()
            grads = [p.grad.clone() for p in model.parameters() if p.grad is not None]
            results.append(([p.detach() for p in preds], grads))
        assert calls == ([6, 1, 1, 1, 1, 1, 1, 4, 2] if norm == "instance" else [6, 6, 6])
        # the upsampler is per image whatever the norm: 2 iterations x (3 | 3 x 1 | 3) samples
        assert up_calls == [3, 3] + [1] * 6 + [3, 3]
        model.image_chunk = None  # automatic: these 32x64 images are below CHUNK_MIN_PIXELS -> one call
        calls.clear()
        model(left, right)
        assert calls == [6]
        big = torch.rand(1, 3, 256, 256) * 255  # CHUNK_MIN_PIXELS: one call per image on CPU (if per-image norm)
        calls.clear()
        model(big, big)
        assert calls == ([1, 1] if norm == "instance" else [2])
        ref_preds, ref_grads = results[0]
        ref_flat = torch.cat([g.flatten() for g in ref_grads])
        for preds, grads in results[1:]:
            for a, b in zip(preds, ref_preds, strict=True):
                torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
            # float32 sums in another order; some entries are ~0 by construction (a conv bias before instance
            # norm), so the gradient is compared as one vector: relative error of its norm
            flat = torch.cat([g.flatten() for g in grads])
            assert float((flat - ref_flat).norm() / ref_flat.norm()) < 1e-5

    def test_feature_detached_lookup(self, monkeypatch: pytest.MonkeyPatch) -> None:
        """D_s is detached before every lookup (RAFT): the lookup never sees a disparity that carries a graph."""
        model = build_model("optstereo", iters=3, **TINY)
        seen: list[bool] = []
        original = model.corr_block.lookup

        def spy(pyramid: list[torch.Tensor], disp: torch.Tensor) -> torch.Tensor:
            seen.append(disp.requires_grad)
            return original(pyramid, disp)

        monkeypatch.setattr(model.corr_block, "lookup", spy)
        preds = model(torch.rand(1, 3, 32, 64) * 255, torch.rand(1, 3, 32, 64) * 255)
        assert seen == [False, False, False]
        assert all(p.requires_grad for p in preds)

    def test_feature_autocast_bf16(self) -> None:
        model = build_model("optstereo", iters=2, **TINY)
        left, right = torch.rand(1, 3, 32, 64) * 255, torch.rand(1, 3, 32, 64) * 255
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            low, full = model(left, right, test_mode=True)
        assert low.dtype == torch.float32 and full.dtype == torch.float32  # D_s accumulates in float32
        assert torch.isfinite(full).all()
        with torch.no_grad():
            _, ref = model(left, right, test_mode=True)
        assert (full - ref).abs().max() < 0.1 * ref.abs().max() + 0.5

    @pytest.mark.parametrize(
        ("left_shape", "right_shape", "match"),
        [
            ((3, 32, 64), (3, 32, 64), r"must be 4-D \(B, 3, H, W\), got \(3, 32, 64\)"),
            ((1, 3, 32, 64), (1, 3, 32, 72), r"shapes differ: \(1, 3, 32, 64\) vs \(1, 3, 32, 72\)"),
            ((1, 1, 32, 64), (1, 1, 32, 64), r"3 channels .* got \(1, 1, 32, 64\)"),
            ((1, 3, 30, 64), (1, 3, 30, 64), r"divisible by 8, got \(30, 64\); pad with .*InputPadder"),
            ((1, 3, 32, 32), (1, 3, 32, 32), r"W must be >= 64 for 4 cost-volume levels, got W = 32"),
        ],
    )
    def test_exception(self, left_shape: tuple, right_shape: tuple, match: str) -> None:
        model = build_model("optstereo", iters=1, **TINY)
        with pytest.raises(ValueError, match=match):
            model(torch.zeros(left_shape), torch.zeros(right_shape))

    @pytest.mark.parametrize("name", ["optstereo", "hitnet"])
    def test_a_float64_pair_is_named(self, name: str) -> None:
        """A float64 pair (NumPy's default, through torch.from_numpy) is named with its fix; uint8 runs."""
        model = build_model(name, iters=1, **(TINY if name == "optstereo" else {})).eval()
        pair = torch.rand(2, 1, 3, 32, 64, dtype=torch.float64) * 255
        with pytest.raises(TypeError, match=r"float32 .* got torch.float64; pass .float\(\)"):
            model(*pair)
        with torch.no_grad():
            model(*pair.to(torch.uint8))
            if name == "optstereo":  # a float64 model takes float64 (gradcheck, numerical comparisons)
                model.double()(*pair)

    def test_exception_iters(self) -> None:
        model = build_model("optstereo", **TINY)
        with pytest.raises(ValueError, match="iters must be >= 1, got 0"):
            model(torch.zeros(1, 3, 32, 64), torch.zeros(1, 3, 32, 64), iters=0)

    def test_smoke_injected_parts(self) -> None:
        """OptStereo is composed from injected blocks; swapping one (here the correlation radius) needs no edits."""
        from optstereo.models.correlation import CorrBlock1D
        from optstereo.models.extractor import FeatureEncoder
        from optstereo.models.update import ConvGRU, DispHead, HiddenInit
        from optstereo.models.upsample import ConvUpsampler

        model = OptStereo(
            feature_encoder=FeatureEncoder(8, widths=(8, 8, 8)),
            corr_block=CorrBlock1D(2, 3),
            hidden_init=HiddenInit(8, 8),
            update_block=ConvGRU(8, 1 + 14, static_dim=8),
            disp_head=DispHead(8, 8),
            upsampler=ConvUpsampler(width=4),
            iters=2,
        )
        with torch.no_grad():
            assert len(model(torch.rand(1, 3, 16, 16) * 255, torch.rand(1, 3, 16, 16) * 255)) == 2


class TestRealData:
    def test_feature_kitti_padded(self, shared_data) -> None:
        """A real KITTI 2015 frame (375 x 1242) through InputPadder and the paper-width model on a crop."""
        import cv2

        frame = shared_data / "kitti15" / "training"
        left = cv2.imread(str(frame / "image_2" / "000000_10.png"))[:, :, ::-1]
        right = cv2.imread(str(frame / "image_3" / "000000_10.png"))[:, :, ::-1]
        assert left.shape == (375, 1242, 3)
        # A 3-row-band crop keeps the run short at C = 256 while H stays not divisible by 8.
        lt, rt = (
            _to_tensor(np.ascontiguousarray(left[200:237, 300:500])),
            _to_tensor(np.ascontiguousarray(right[200:237, 300:500])),
        )
        padder = InputPadder(lt.shape, divis_by=8)
        lp, rp = padder.pad(lt, rt)
        model = build_model("optstereo", iters=2).eval()
        with torch.no_grad():
            _, full = model(lp, rp, test_mode=True)
        out = padder.unpad(full)
        assert out.shape == (1, 1, 37, 200) and torch.isfinite(out).all()


def _overfit(steps: int, iters: int, lr: float) -> tuple[float, float]:
    torch.manual_seed(0)
    left, right, label = _two_plane_pair(np.random.default_rng(0))
    model = build_model("optstereo", iters=iters, feature_dim=32, hidden_dim=32, head_dim=32, upsample_dim=8)
    return overfit_epe(model, left, right, label, steps, lr)


class TestOverfit:
    def test_feature_short(self) -> None:
        """40 Adam steps with L_P on one two-plane pair (4 px / 12 px) cut the EPE by far more than 30 %
        (measured: ~12 px -> ~2 px)."""
        start, end = _overfit(40, iters=3, lr=2e-3)
        assert start > 3.0
        assert end < 0.5 * start, (start, end)

    @pytest.mark.slow
    def test_feature_long(self) -> None:
        start, end = _overfit(300, iters=4, lr=1e-3)
        assert end < 0.1 * start and end < 1.0, (start, end)

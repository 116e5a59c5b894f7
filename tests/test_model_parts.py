"""OptStereo building blocks against slow hand-written references (small random tensors, float64 where exact)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from optstereo.models.correlation import CorrBlock1D, build_pyramid, correlation_volume, lookup_pyramid
from optstereo.models.extractor import FeatureEncoder
from optstereo.models.layers import ResidualBlock, SeparableBlock, make_norm
from optstereo.models.update import ConvGRU, DispHead, HiddenInit
from optstereo.models.upsample import ConvexUpsampler, ConvUpsampler, upsample_disp


def _naive_correlation(fl: np.ndarray, fr: np.ndarray) -> np.ndarray:
    b, c, h, w = fl.shape
    out = np.zeros((b, h, w, w))
    for bi in range(b):
        for i in range(h):
            for j in range(w):
                for k in range(w):
                    out[bi, i, j, k] = sum(fl[bi, ch, i, j] * fr[bi, ch, i, k] for ch in range(c)) / math.sqrt(c)
    return out


def _naive_lookup(pyramid: list[np.ndarray], disp: np.ndarray, radius: int) -> np.ndarray:
    """Linear interpolation of a zero-padded row written as a sum of hat functions (no floor/gather)."""
    b, _, h, w = disp.shape
    levels = len(pyramid)
    out = np.zeros((b, levels * (2 * radius + 1), h, w))
    for bi in range(b):
        for i in range(h):
            for j in range(w):
                for k, vol in enumerate(pyramid):
                    row = vol[bi, i, j]
                    n = np.arange(row.shape[0])
                    for t, dj in enumerate(range(-radius, radius + 1)):
                        x = (j - disp[bi, 0, i, j]) / 2**k + dj
                        out[bi, k * (2 * radius + 1) + t, i, j] = np.sum(row * np.maximum(0.0, 1.0 - np.abs(x - n)))
    return out


class TestCorrelation:
    def test_feature_volume(self) -> None:
        g = torch.Generator().manual_seed(0)
        fl = torch.randn(2, 5, 3, 7, generator=g, dtype=torch.float64)
        fr = torch.randn(2, 5, 3, 7, generator=g, dtype=torch.float64)
        vol = correlation_volume(fl, fr)
        assert vol.shape == (2, 3, 7, 7) and vol.dtype == torch.float32
        np.testing.assert_allclose(vol.numpy(), _naive_correlation(fl.numpy(), fr.numpy()), rtol=1e-5, atol=1e-5)
        unscaled = correlation_volume(fl, fr, scale=False)
        np.testing.assert_allclose(unscaled.numpy(), vol.numpy() * math.sqrt(5), rtol=1e-5)

    def test_feature_pyramid_averages(self) -> None:
        vol = torch.randn(1, 2, 11, 11, generator=torch.Generator().manual_seed(1))
        pyr = build_pyramid(vol, 4)
        assert [p.shape[-1] for p in pyr] == [11, 5, 2, 1]  # floor(W / 2^k): the odd last column is dropped
        v = vol.numpy()
        np.testing.assert_allclose(pyr[1].numpy()[..., 3], (v[..., 6] + v[..., 7]) / 2, rtol=1e-6)
        np.testing.assert_allclose(pyr[2].numpy()[..., 1], v[..., 4:8].mean(-1), rtol=1e-5)
        np.testing.assert_allclose(pyr[3].numpy()[..., 0], v[..., 0:8].mean(-1), rtol=1e-5)

    @pytest.mark.parametrize(("levels", "radius"), [(4, 4), (1, 4), (4, 1), (3, 2)])
    def test_feature_lookup_matches_naive(self, levels: int, radius: int) -> None:
        g = torch.Generator().manual_seed(2)
        vol = torch.randn(2, 3, 16, 16, generator=g)
        pyr = build_pyramid(vol, levels)
        # Real-valued disparities, some negative and some far beyond the row, so taps fall outside [0, W_k - 1].
        disp = torch.empty(2, 1, 3, 16).uniform_(-6.0, 24.0, generator=g)
        disp[0, 0, 0, :4] = torch.tensor([0.0, 2.0, 15.5, -0.5])
        got = lookup_pyramid(pyr, disp, radius)
        assert got.shape == (2, levels * (2 * radius + 1), 3, 16)
        want = _naive_lookup([p.double().numpy() for p in pyr], disp.double().numpy(), radius)
        np.testing.assert_allclose(got.numpy(), want, rtol=1e-5, atol=1e-5)

    def test_feature_zero_disparity_reads_diagonal(self) -> None:
        vol = torch.randn(1, 2, 8, 8, generator=torch.Generator().manual_seed(3))
        got = lookup_pyramid([vol], torch.zeros(1, 1, 2, 8), radius=0)
        np.testing.assert_allclose(got[0, 0].numpy(), torch.diagonal(vol[0], dim1=1, dim2=2).numpy())

    def test_smoke_block(self) -> None:
        block = CorrBlock1D(4, 4)
        assert block.out_channels == 36 and block.min_width == 8
        fl = torch.randn(1, 8, 2, 16)
        fr = torch.randn(1, 8, 2, 16)
        out = block.lookup(block.build_pyramid(fl, fr), torch.zeros(1, 1, 2, 16))
        assert out.shape == (1, 36, 2, 16)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="num_levels >= 1"):
            CorrBlock1D(0, 4)

    def test_gradcheck(self) -> None:
        """Gradients flow into the features through the volume and the interpolated lookup."""
        g = torch.Generator().manual_seed(4)
        fl = torch.randn(1, 3, 2, 8, generator=g, dtype=torch.float64, requires_grad=True)
        fr = torch.randn(1, 3, 2, 8, generator=g, dtype=torch.float64, requires_grad=True)
        disp = torch.empty(1, 1, 2, 8, dtype=torch.float64).uniform_(0.2, 5.7, generator=g)

        def fn(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
            # float64 end to end: the module computes in float32, so check the pure-math path in float64 here
            vol = torch.einsum("bchw,bchv->bhwv", a, b) / math.sqrt(3)
            return lookup_pyramid(build_pyramid(vol, 2), disp, 2)

        assert torch.autograd.gradcheck(fn, (fl, fr))


class TestConvGRU:
    def test_feature_matches_equation(self) -> None:
        """Module output == eq. (GRU) on the concatenated input [h, D, M, F_l] with the re-assembled weights."""
        torch.manual_seed(5)
        hid, dyn, stat = 6, 4, 5
        gru = ConvGRU(hid, dyn, static_dim=stat).double()
        h = torch.randn(2, hid, 5, 7, dtype=torch.float64)
        x_dyn = torch.randn(2, dyn, 5, 7, dtype=torch.float64)
        feat = torch.randn(2, stat, 5, 7, dtype=torch.float64)
        got = gru(h, x_dyn, gru.precompute(feat))

        ws_z, ws_r, ws_q = gru.static.weight.chunk(3, dim=0)
        wd_z, wd_r = gru.convzr.weight.chunk(2, dim=0)
        b_z, b_r = gru.convzr.bias.chunk(2)
        w_z = torch.cat([wd_z, ws_z], dim=1)
        w_r = torch.cat([wd_r, ws_r], dim=1)
        w_q = torch.cat([gru.convq.weight, ws_q], dim=1)
        x = torch.cat([x_dyn, feat], dim=1)  # x^k = [D, M_l, F_l]
        hx = torch.cat([h, x], dim=1)
        z = torch.sigmoid(F.conv2d(hx, w_z, b_z, padding=1))
        r = torch.sigmoid(F.conv2d(hx, w_r, b_r, padding=1))
        q = torch.tanh(F.conv2d(torch.cat([r * h, x], dim=1), w_q, gru.convq.bias, padding=1))
        want = (1 - z) * h + z * q
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)

    def test_feature_without_static(self) -> None:
        torch.manual_seed(6)
        gru = ConvGRU(3, 2).double()
        assert gru.precompute(torch.zeros(1, 1, 1, 1)) is None
        h = torch.randn(1, 3, 4, 4, dtype=torch.float64)
        x = torch.randn(1, 2, 4, 4, dtype=torch.float64)
        hx = torch.cat([h, x], 1)
        w_z, w_r = gru.convzr.weight.chunk(2, dim=0)
        b_z, b_r = gru.convzr.bias.chunk(2)
        z = torch.sigmoid(F.conv2d(hx, w_z, b_z, padding=1))
        r = torch.sigmoid(F.conv2d(hx, w_r, b_r, padding=1))
        q = torch.tanh(gru.convq(torch.cat([r * h, x], 1)))
        torch.testing.assert_close(gru(h, x), (1 - z) * h + z * q)


class TestSmallBlocks:
    def test_cardinality_encoder(self) -> None:
        enc = FeatureEncoder(16, widths=(8, 8, 8))
        assert enc(torch.randn(2, 3, 32, 64)).shape == (2, 16, 4, 8)
        n_blocks = sum(isinstance(m, ResidualBlock) for m in enc.modules())
        assert n_blocks == 6  # two at 1/2, two at 1/4, two at 1/8

    def test_feature_separable_stage1(self) -> None:
        """stage1 = "separable": two SeparableBlock at 1/2 (identity at the start), the rest as RAFT's."""
        torch.manual_seed(0)
        enc = FeatureEncoder(16, widths=(8, 8, 8), stage1="separable")
        assert [type(b) for b in enc.layer1] == [SeparableBlock, SeparableBlock]
        assert sum(isinstance(m, ResidualBlock) for m in enc.modules()) == 4
        x = torch.rand(1, 8, 6, 10)
        torch.testing.assert_close(enc.layer1(x), x, rtol=0, atol=0)  # pw2 = 0 after the encoder's own init
        block = SeparableBlock(8)
        for conv in (block.pw2, block.dw1):
            torch.nn.init.normal_(conv.weight)
        y = torch.relu(block.pw1(block.dw1(x)))
        ref = torch.relu(x + F.conv2d(F.conv2d(y, block.dw2.weight, block.dw2.bias, padding=2, groups=8),
                                      block.pw2.weight, block.pw2.bias))
        torch.testing.assert_close(block(x), ref)
        with pytest.raises(ValueError, match="stage1 must be"):
            FeatureEncoder(16, stage1="mobile")

    def test_feature_separable_stage2(self) -> None:
        """stage2 = "separable": a strided SeparableBlock 8 -> 12 with a 1x1 shortcut, then SeparableBlock(12); the
        strided block against F.conv2d written out, and its start relu(shortcut(x))."""
        torch.manual_seed(1)
        enc = FeatureEncoder(16, widths=(8, 12, 8), stage2="separable")
        down, same = enc.layer2
        assert type(down) is SeparableBlock and type(same) is SeparableBlock
        assert isinstance(same.shortcut, torch.nn.Identity) and down.shortcut.stride == (2, 2)
        assert enc(torch.rand(1, 3, 32, 64)).shape == (1, 16, 4, 8)
        x = torch.rand(1, 8, 7, 10)
        short = F.conv2d(x, down.shortcut.weight, down.shortcut.bias, stride=2)
        torch.testing.assert_close(down(x), torch.relu(short), rtol=0, atol=0)  # pw2 = 0 at the start
        torch.nn.init.normal_(down.pw2.weight)
        y = torch.relu(F.conv2d(F.conv2d(x, down.dw1.weight, down.dw1.bias, stride=2, padding=2, groups=8),
                                down.pw1.weight, down.pw1.bias))
        assert y.shape == (1, 12, 4, 5)
        ref = torch.relu(short + F.conv2d(F.conv2d(y, down.dw2.weight, down.dw2.bias, padding=2, groups=12),
                                          down.pw2.weight, down.pw2.bias))
        torch.testing.assert_close(down(x), ref)
        with pytest.raises(ValueError, match="stage2 must be"):
            FeatureEncoder(16, stage2="mobile")

    def test_cardinality_heads(self) -> None:
        h = torch.randn(2, 8, 4, 8)
        assert DispHead(8, 16)(h).shape == (2, 1, 4, 8)
        h0 = HiddenInit(5, 8)(torch.randn(2, 5, 4, 8))
        assert h0.shape == (2, 8, 4, 8) and h0.abs().max() <= 1.0

    def test_exception_norm(self) -> None:
        with pytest.raises(ValueError, match="unknown norm 'layer'"):
            make_norm("layer", 4)

    def test_feature_upsample_scales_values(self) -> None:
        low = torch.full((1, 1, 2, 3), 1.5)
        up = upsample_disp(low)
        assert up.shape == (1, 1, 16, 24)
        torch.testing.assert_close(up, torch.full_like(up, 12.0))

    def test_feature_conv_upsampler_residual(self) -> None:
        ups = ConvUpsampler(width=4)
        torch.nn.init.zeros_(ups.conv2.weight)
        torch.nn.init.zeros_(ups.conv2.bias)
        low = torch.rand(1, 1, 2, 3) * 4
        out = ups(low, torch.zeros(1, 1, 2, 3), torch.zeros(1, 3, 16, 24))
        torch.testing.assert_close(out, upsample_disp(low))  # zero residual -> plain x8 bilinear upsampling

    def test_feature_convex_constant(self) -> None:
        """A convex combination of a constant 1/8 disparity d is 8 d everywhere (also at the zero-padded border,
        where the learned weights are random, so only the interior is constant)."""
        ups = ConvexUpsampler(hidden_dim=4, width=8)
        low = torch.full((1, 1, 3, 4), 2.0)
        out = ups(low, torch.randn(1, 4, 3, 4), torch.zeros(1, 3, 24, 32))
        assert out.shape == (1, 1, 24, 32)
        torch.testing.assert_close(out[..., 8:16, 8:24], torch.full((1, 1, 8, 16), 16.0))


def _naive_instance_norm(x: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    mean = x.mean(axis=(2, 3), keepdims=True)
    var = ((x - mean) ** 2).mean(axis=(2, 3), keepdims=True)
    return (x - mean) / np.sqrt(var + eps)


class TestChannelsLast:
    """The channels-last path of the encoder and upsampler (bf16 on CPU) computes what the NCHW path computes."""

    def test_instance_norm_fast_path_matches_reference_and_grads(self) -> None:
        torch.manual_seed(3)
        x = (torch.randn(1, 5, 7, 9, dtype=torch.float64) * 3 + 1).contiguous(memory_format=torch.channels_last)
        x.requires_grad_(True)
        norm = make_norm("instance", 5)
        y = norm(x)
        assert y.is_contiguous(memory_format=torch.channels_last) and not y.is_contiguous()  # the fast path ran
        np.testing.assert_allclose(y.detach().numpy(), _naive_instance_norm(x.detach().numpy()), atol=1e-12)
        weights = torch.randn(1, 5, 7, 9, dtype=torch.float64)
        (y * weights).sum().backward()
        x_ref = x.detach().contiguous().requires_grad_(True)
        (torch.nn.InstanceNorm2d(5)(x_ref) * weights).sum().backward()
        torch.testing.assert_close(x.grad, x_ref.grad, rtol=1e-10, atol=1e-12)

    def test_instance_norm_other_inputs_take_the_standard_path(self) -> None:
        torch.manual_seed(4)
        x = torch.randn(2, 3, 4, 6).contiguous(memory_format=torch.channels_last)  # B = 2: statistics per image
        ref = _naive_instance_norm(x.numpy().astype(np.float64))
        np.testing.assert_allclose(make_norm("instance", 3)(x).numpy(), ref, atol=1e-5)
        y = make_norm("instance", 3)(torch.randn(1, 3, 4, 6))  # NCHW stays NCHW
        assert y.is_contiguous()

    @pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.trace: what export=torchscript uses
    def test_use_channels_last_only_in_eager_cpu_and_not_for_float32_grad(self) -> None:
        from optstereo.models.layers import use_channels_last

        x = torch.zeros(1, 3, 8, 8)
        assert use_channels_last(x) and not use_channels_last(x, exact_float32_grad=True)
        assert use_channels_last(x.bfloat16(), exact_float32_grad=True)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert use_channels_last(x, exact_float32_grad=True)
        with torch.no_grad():  # no backward: the channels-last forward is as exact as NCHW
            assert use_channels_last(x, exact_float32_grad=True)
        assert not use_channels_last(torch.zeros(3, 8, 8))
        seen = []
        torch.jit.trace(lambda t: (seen.append(use_channels_last(t)), t * 2)[1], (x,), check_trace=False)
        assert seen == [False]

    def test_encoder_bf16_channels_last_close_to_nchw_and_returns_nchw(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import optstereo.models.extractor as extractor

        torch.manual_seed(5)
        enc = FeatureEncoder(output_dim=16, widths=(8, 12, 16)).eval()
        x = torch.rand(1, 3, 32, 48) * 2 - 1
        with torch.no_grad():
            ref = enc(x)  # float32
            with torch.autocast("cpu", dtype=torch.bfloat16):
                fast = enc(x).float()
                monkeypatch.setattr(extractor, "use_channels_last", lambda t, **kw: False)
                slow = enc(x).float()
        assert fast.is_contiguous() and fast.shape == (1, 16, 4, 6)
        # the two bf16 paths differ by bf16 rounding only: no further from each other than bf16 is from float32
        assert float((fast - slow).abs().max()) <= 2 * float((slow - ref).abs().max()) + 1e-6
        assert float((fast - ref).abs().mean()) < 0.05 * float(ref.abs().mean())

    def test_encoder_float32_inference_channels_last_same_values(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import optstereo.models.extractor as extractor

        torch.manual_seed(7)
        enc = FeatureEncoder(output_dim=16, widths=(8, 12, 16)).eval()
        x = torch.rand(1, 3, 32, 48) * 2 - 1
        with torch.no_grad():
            fast = enc(x)
            monkeypatch.setattr(extractor, "use_channels_last", lambda t, **kw: False)
            slow = enc(x)
        assert fast.is_contiguous()
        torch.testing.assert_close(fast, slow, rtol=1e-5, atol=1e-5)

    def test_upsampler_channels_last_same_values(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import optstereo.models.upsample as upsample

        torch.manual_seed(6)
        up = ConvUpsampler(width=8).double()
        disp, image = torch.rand(1, 1, 4, 6, dtype=torch.float64) * 3, torch.rand(1, 3, 32, 48, dtype=torch.float64)
        fast = up(disp, None, image)
        monkeypatch.setattr(upsample, "use_channels_last", lambda t, **kw: False)
        torch.testing.assert_close(fast, up(disp, None, image), rtol=1e-12, atol=1e-12)
        assert fast.is_contiguous()

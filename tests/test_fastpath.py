"""The engineered CPU inference path (issue 52, optstereo.inference.fastpath / .winograd): the plain path's outputs
kept (a tiny random model, the shipped weights on a real KITTI crop), its parts against the plain ones, the cases
that fall back to ``OptStereo.forward``, and the state dict left alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from conftest import TINY, TINY_HITNET, kitti_crop

from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors
from optstereo.inference import fastpath
from optstereo.inference.engine import infer, network_pass
from optstereo.inference.fastpath import EngineeredOptStereo, engineer, engineering, supported
from optstereo.inference.winograd import winograd_conv3x3, winograd_weight
from optstereo.models import build_model
from optstereo.models.correlation import build_pyramid, correlation_volume, lookup_pyramid

pytestmark = pytest.mark.usefixtures("one_torch_thread")

MEAN_TOL = 0.01  # px: issue 52's bound on the mean difference from the plain path
MAX_TOL = 0.05  # px: the largest difference allowed at any pixel (measured: < 3e-4 px on full KITTI frames)


def tiny_model(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return build_model("optstereo", **TINY, iters=4).eval()


def both_paths(model: torch.nn.Module, *args: torch.Tensor, **kwargs: object) -> tuple[torch.Tensor, torch.Tensor]:
    """Full-resolution test-mode output of the plain path and of the engineered one."""
    fast = engineer(model)
    assert isinstance(fast, EngineeredOptStereo)
    with torch.inference_mode():
        with engineering(False):
            plain = fast(*args, test_mode=True, **kwargs)
        engineered = fast(*args, test_mode=True, **kwargs)
    for p, e in zip(plain, engineered, strict=True):
        assert p.shape == e.shape
    return plain[1], engineered[1]


def assert_close_px(plain: np.ndarray | torch.Tensor, engineered: np.ndarray | torch.Tensor) -> None:
    diff = np.abs(np.asarray(plain, np.float64) - np.asarray(engineered, np.float64))
    assert diff.mean() <= MEAN_TOL and diff.max() <= MAX_TOL, (diff.mean(), diff.max())


class TestEngineeredPass:
    @pytest.mark.parametrize("shape", [(1, 3, 64, 128), (1, 3, 40, 72), (2, 3, 32, 64)])
    def test_feature_tiny_model(self, shape: tuple[int, ...]) -> None:
        """Random weights and images; odd 1/8 sizes (5 x 9) cut the Winograd tiles; a batch takes direct convs."""
        torch.manual_seed(1)
        left, right = torch.rand(shape) * 255, torch.rand(shape) * 255
        assert_close_px(*both_paths(tiny_model(), left, right))

    def test_feature_start_and_iters(self) -> None:
        torch.manual_seed(2)
        left, right = torch.rand(1, 3, 48, 96) * 255, torch.rand(1, 3, 48, 96) * 255
        start = torch.rand(1, 1, 6, 12) * 3
        assert_close_px(*both_paths(tiny_model(), left, right, iters=3, disp_init=start))
        with pytest.raises(ValueError, match="disp_init must be"):
            both_paths(tiny_model(), left, right, disp_init=start[..., :6])

    def test_feature_without_winograd(self) -> None:
        torch.manual_seed(3)
        left, right = torch.rand(1, 3, 64, 128) * 255, torch.rand(1, 3, 64, 128) * 255
        with engineering(True, winograd=False):
            assert_close_px(*both_paths(tiny_model(), left, right))

    def test_feature_shipped_weights_on_kitti(self, shared_data: Path) -> None:
        """The shipped model, one pass on a real 128 x 512 KITTI crop: plain vs engineered in float32 (its int8
        encoder is held to float32's in tests/test_int8.py)."""
        model = load_model("pretrained")
        assert isinstance(model, EngineeredOptStereo)
        left, right = kitti_crop(shared_data, 128, 512)
        with engineering(False):
            plain = network_pass(model, left, right)
        with engineering(True, int8=False):
            engineered = network_pass(model, left, right)
        assert_close_px(plain, engineered)
        assert np.median(plain) > 5  # a real disparity map, not two zero maps

    def test_feature_infer_front_door(self, rng: np.random.Generator) -> None:
        model = engineer(tiny_model())
        left = rng.integers(0, 256, (37, 70, 3), dtype=np.uint8)
        right = rng.integers(0, 256, (37, 70, 3), dtype=np.uint8)
        with engineering(False):
            plain = infer(model, left, right)
        assert_close_px(plain, infer(model, left, right))


class TestFallbacks:
    def test_plain_forward_outside_float32_cpu_inference(self) -> None:
        """Training mode, autograd and autocast run OptStereo.forward itself (bit for bit)."""
        torch.manual_seed(4)
        model = tiny_model()
        fast = engineer(model)
        left, right = torch.rand(1, 3, 32, 64) * 255, torch.rand(1, 3, 32, 64) * 255
        preds = fast(left, right)  # training output: a list, with gradients
        assert isinstance(preds, list) and preds[-1].requires_grad
        torch.testing.assert_close(preds[-1], model(left, right)[-1], rtol=0, atol=0)
        with torch.autocast("cpu", dtype=torch.bfloat16), torch.no_grad():
            torch.testing.assert_close(fast(left, right, test_mode=True)[1], model(left, right, test_mode=True)[1],
                                       rtol=0, atol=0)

    def test_engineer_keeps_state_and_parameters(self) -> None:
        model = tiny_model()
        model.inference_config = "kept"
        fast = engineer(model)
        assert fast.state_dict().keys() == model.state_dict().keys()
        assert all(a is b for a, b in zip(fast.parameters(), model.parameters(), strict=True))
        assert fast.inference_config == "kept" and not fast.training
        assert engineer(fast) is fast  # already engineered: returned as is

    def test_feature_unknown_encoder_block_runs_as_it_is(self) -> None:
        """A block the engineered encoder does not know (here a 1x1 conv + ReLU in layer1) is called as a module."""
        torch.manual_seed(5)
        fast = engineer(tiny_model())
        width = fast.feature_encoder.layer1[0].conv1.out_channels
        fast.feature_encoder.layer1[1] = torch.nn.Sequential(torch.nn.Conv2d(width, width, 1), torch.nn.ReLU())
        left, right = torch.rand(1, 3, 48, 96) * 255, torch.rand(1, 3, 48, 96) * 255
        assert_close_px(*both_paths(fast, left, right))

    def test_feature_separable_stages(self) -> None:
        """stage1 and stage2 separable (the strided block's 1x1 shortcut included), every weight random."""
        torch.manual_seed(6)
        model = build_model("optstereo", **TINY, iters=3, stage1="separable", stage2="separable").eval()
        for block in (*model.feature_encoder.layer1, *model.feature_encoder.layer2):
            torch.nn.init.normal_(block.pw2.weight, std=0.2)
        left, right = torch.rand(1, 3, 48, 96) * 255, torch.rand(1, 3, 48, 96) * 255
        assert supported(model)
        assert_close_px(*both_paths(model, left, right))

    def test_engineer_leaves_other_models(self) -> None:
        hitnet = build_model("hitnet", **TINY_HITNET)
        assert engineer(hitnet) is hitnet
        convex = build_model("optstereo", **TINY, upsampler="convex")
        assert type(engineer(convex)) is EngineeredOptStereo  # the upsampler is called as it is

    def test_feature_model_loaded_under_inference_mode(self, tmp_path: Path) -> None:
        """A model loaded inside ``torch.inference_mode`` (its weights inference tensors, without a version) runs
        the engineered pass, equal to the plain one, and follows a weight changed there."""
        path = export_safetensors(tmp_path / "tiny.safetensors", tiny_model(7))
        left, right = torch.rand(1, 3, 32, 64) * 255, torch.rand(1, 3, 32, 64) * 255
        with torch.inference_mode():
            fast = load_model(path)
            assert fast.update_block.convq.weight.is_inference()
            assert_close_px(*both_paths(fast, left, right))
            fast.update_block.convq.weight.mul_(0.5)
            assert_close_px(*both_paths(fast, left, right))

    def test_winograd_weights_follow_the_parameters(self) -> None:
        """A weight changed in place (as an optimiser step does) or replaced re-makes its cached transform."""
        torch.manual_seed(5)
        fast = engineer(tiny_model())
        left, right = torch.rand(1, 3, 32, 64) * 255, torch.rand(1, 3, 32, 64) * 255
        with torch.no_grad():
            fast(left, right, test_mode=True)
            fast.update_block.convq.weight.mul_(0.5)
            fast.disp_head.conv1.weight.mul_(2.0)
        assert_close_px(*both_paths(fast, left, right))
        old = fast.update_block.convzr.weight
        new = torch.nn.Parameter(old.detach() * 1.5)
        with torch.no_grad():
            while new._version < old._version:  # the same version number: only the identity tells them apart
                new.add_(0.0)
        fast.update_block.convzr.weight = new
        assert_close_px(*both_paths(fast, left, right))


class TestParts:
    def test_lookup_equals_plain(self) -> None:
        """The padded single-gather lookup gives the plain lookup's values, taps outside every level included."""
        torch.manual_seed(6)
        fl, fr = torch.randn(2, 16, 5, 37), torch.randn(2, 16, 5, 37)
        pyramid = build_pyramid(correlation_volume(fl, fr), 4)
        volume, widths = fastpath.padded_pyramid(fl.contiguous(memory_format=torch.channels_last),
                                                 fr.contiguous(memory_format=torch.channels_last), 4, True)
        assert widths == [37, 18, 9, 4]
        disp = torch.rand(2, 1, 5, 37) * 60 - 15  # negative, in range and far beyond the row
        got = fastpath.lookup(volume, fastpath.lookup_taps(widths, 3, disp.device), disp).permute(0, 3, 1, 2)
        torch.testing.assert_close(got, lookup_pyramid(pyramid, disp, 3), rtol=1e-6, atol=1e-6)

    @pytest.mark.parametrize(("c_in", "c_out", "h", "w"), [(5, 7, 1, 1), (3, 4, 5, 9), (16, 8, 12, 13), (8, 3, 8, 4)])
    def test_winograd_equals_direct(self, c_in: int, c_out: int, h: int, w: int) -> None:
        torch.manual_seed(7)
        x = torch.randn(1, c_in, h, w).contiguous(memory_format=torch.channels_last)
        weight, bias = torch.randn(c_out, c_in, 3, 3), torch.randn(c_out)
        ref = F.conv2d(x.double(), weight.double(), bias.double(), padding=1)
        got = winograd_conv3x3(x, winograd_weight(weight), bias)
        assert got.shape == ref.shape
        torch.testing.assert_close(got.double(), ref, rtol=0, atol=1e-4 * ref.abs().max().item())
        torch.testing.assert_close(winograd_conv3x3(x, winograd_weight(weight), None).double(),
                                   ref - bias.double().view(1, -1, 1, 1), rtol=0, atol=1e-4 * ref.abs().max().item())

    def test_winograd_exception(self) -> None:
        with pytest.raises(ValueError, match="3x3 kernel"):
            winograd_weight(torch.zeros(4, 4, 5, 5))
        with pytest.raises(ValueError, match="one image of 4 channels"):
            winograd_conv3x3(torch.zeros(2, 4, 8, 8), winograd_weight(torch.zeros(4, 4, 3, 3)), None)


class TestWinogradChoice:
    """``fastpath.faster_of``: the faster of Winograd and direct GRU convolutions, timed once per process."""

    @staticmethod
    def _clock_where(monkeypatch: pytest.MonkeyPatch, slow: str) -> None:
        """A fake clock under which the ``slow`` way ("winograd" or "direct") takes 1 s a call, the other 0."""
        ticks = {"now": 0.0}

        def clock() -> float:
            return ticks["now"]

        real_conv, real_winograd = torch.nn.Conv2d.forward, fastpath.winograd_conv3x3

        def charge(fn):  # noqa: ANN001, ANN202 - a test wrapper
            def run(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
                ticks["now"] += 1.0
                return fn(*args, **kwargs)
            return run

        monkeypatch.setattr(fastpath, "_clock", clock)
        if slow == "winograd":
            monkeypatch.setattr(fastpath, "winograd_conv3x3", charge(real_winograd))
        else:
            monkeypatch.setattr(torch.nn.Conv2d, "forward", charge(real_conv))

    @pytest.mark.parametrize("slow", ["winograd", "direct"])
    def test_the_faster_way_is_kept_and_the_output_is_the_plain_paths(
            self, monkeypatch: pytest.MonkeyPatch, slow: str) -> None:
        monkeypatch.setattr(fastpath, "_choices", {})
        self._clock_where(monkeypatch, slow)
        torch.manual_seed(7)
        left, right = torch.rand(1, 3, 32, 64) * 255, torch.rand(1, 3, 32, 64) * 255
        assert_close_px(*both_paths(tiny_model(), left, right))
        choices = fastpath.winograd_choices()
        assert sorted(name.split()[0] for name in choices) == ["head", "q", "zr"]
        assert set(choices.values()) == {slow == "direct"}

    def test_one_calibration_per_convolution_and_process(self, monkeypatch: pytest.MonkeyPatch) -> None:
        monkeypatch.setattr(fastpath, "_choices", {})
        calls = {"n": 0}
        real = fastpath.winograd_conv3x3

        def counted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            calls["n"] += 1
            return real(*args, **kwargs)

        monkeypatch.setattr(fastpath, "winograd_conv3x3", counted)
        fast = engineer(tiny_model())
        left, right = torch.rand(1, 3, 32, 64) * 255, torch.rand(1, 3, 32, 64) * 255
        with torch.no_grad(), engineering(True, winograd="auto"):
            fast(left, right, iters=4, test_mode=True)
            first = calls["n"]
            fast(left, right, iters=4, test_mode=True)
        # three convolutions, CALIBRATION_RUNS timed Winograd runs each, once; then Winograd only where it won
        assert first >= 3 * fastpath.CALIBRATION_RUNS
        assert calls["n"] - first == 4 * sum(fastpath.winograd_choices().values())

    def test_forced_ways_skip_the_calibration(self, monkeypatch: pytest.MonkeyPatch) -> None:
        monkeypatch.setattr(fastpath, "_choices", {})
        fast = engineer(tiny_model())
        left, right = torch.rand(1, 3, 32, 64) * 255, torch.rand(1, 3, 32, 64) * 255
        for way in (True, False):
            with torch.no_grad(), engineering(True, winograd=way):
                fast(left, right, test_mode=True)
        assert fastpath.winograd_choices() == {}

    def test_no_winograd_weights_are_made_where_direct_won(self, monkeypatch: pytest.MonkeyPatch) -> None:
        monkeypatch.setattr(fastpath, "_choices", {})
        self._clock_where(monkeypatch, "winograd")
        fast = engineer(tiny_model())
        left, right = torch.rand(1, 3, 32, 64) * 255, torch.rand(1, 3, 32, 64) * 255
        with torch.no_grad():
            fast(left, right, test_mode=True)  # calibrates: direct wins
        assert set(fastpath.winograd_choices().values()) == {False}

        def no_transform(*args: object) -> None:
            raise AssertionError("a Winograd weight was made for a convolution that runs direct")

        monkeypatch.setattr(EngineeredOptStereo, "_winograd", no_transform)
        with torch.no_grad():
            fast(left, right, test_mode=True)

"""The coarse-to-fine start (optstereo.inference.cascade): grid units by hand, the model's disp_init, the trainer's
draw and
infer's passes with fake networks whose outputs are known (the pass sequence itself: tests/test_inference_path.py)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import TINY, Echo, StartEcho, kitti_crop

from optstereo.inference.cascade import choose, coarse_start, grid_start, half_size, jump_limit, photometric_select
from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import infer
from optstereo.models import build_model

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_grid_start_by_hand() -> None:
    disp = torch.full((1, 1, 16, 24), 16.0)
    disp[..., :8, :8] = torch.arange(64, dtype=torch.float32).reshape(8, 8)  # mean 31.5
    grid = grid_start(disp)
    assert grid.shape == (1, 1, 2, 3)
    assert grid[0, 0, 0, 0] == pytest.approx(31.5 / 8) and torch.all(grid.flatten()[1:] == 2.0)
    with pytest.raises(ValueError, match="divisible by 8"):
        grid_start(torch.zeros(1, 1, 12, 16))


def test_half_size() -> None:
    assert half_size(256, 640) == (128, 320)
    assert half_size(100, 300) == (48, 144)
    assert half_size(10, 12) == (8, 8)
    assert half_size(64, 120, min_width=64) == (32, 64)  # a narrow pair's coarse pass keeps the network's minimum
    assert half_size(64, 64, min_width=64) == (32, 64)


def test_coarse_start_on_a_pair_narrower_than_twice_the_minimum() -> None:
    """120 px wide: half would be 56 px, below the 4-level pyramid's 64 (it used to raise); the start keeps 64."""
    torch.manual_seed(0)
    model = build_model("optstereo", feature_dim=16, hidden_dim=16, head_dim=16, iters=1).eval()
    assert model.min_width == 64
    x = torch.rand(1, 3, 64, 120) * 255
    start = coarse_start(model, x, x, iters=1)
    assert start.shape == (1, 1, 8, 15) and torch.isfinite(start).all()


def test_coarse_start_units() -> None:
    # red 40 everywhere: the half-size pass (16 x 32) answers 40 px of ITS pair = 80 px of the 32 x 64 batch, which
    # is 10 px on the 1/8 grid (hand-computed)
    left = torch.full((2, 3, 32, 64), 40.0)
    start = coarse_start(Echo(), left, left, iters=None)
    assert start.shape == (2, 1, 4, 8)
    torch.testing.assert_close(start, torch.full((2, 1, 4, 8), 10.0))


class TestModel:
    def test_zero_start_is_the_default(self) -> None:
        torch.manual_seed(0)
        model = build_model("optstereo", **TINY, iters=2).eval()
        left, right = torch.rand(1, 3, 64, 128) * 255, torch.rand(1, 3, 64, 128) * 255
        with torch.no_grad():
            plain = model(left, right, test_mode=True)
            zero = model(left, right, test_mode=True, disp_init=torch.zeros(1, 1, 8, 16))
            moved = model(left, right, test_mode=True, disp_init=torch.full((1, 1, 8, 16), 3.0))
        for a, b in zip(plain, zero, strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
        assert not torch.allclose(plain[1], moved[1])
        with pytest.raises(ValueError, match="disp_init must be"):
            model(left, right, test_mode=True, disp_init=torch.zeros(1, 1, 4, 16))

    def test_no_gradient_into_the_start(self) -> None:
        torch.manual_seed(0)
        model = build_model("optstereo", **TINY, iters=2)
        left, right = torch.rand(1, 3, 64, 128) * 255, torch.rand(1, 3, 64, 128) * 255
        start = torch.full((1, 1, 8, 16), 2.0, requires_grad=True)
        preds = model(left, right, iters=2, disp_init=start)
        sum(p.mean() for p in preds).backward()
        assert start.grad is None
        assert any(p.grad is not None for p in model.parameters())


def test_infer_cascade_follows_the_units() -> None:
    # input scale 1: the coarse pass (optstereo.inference.cascade.coarse_start on the padded pair at half size) answers
    # red R
    # in half-size px = 2R px of the pair; the final pass starts from that and StartEcho hands the start back: 2R,
    # where the zero start answers R (hand-computed)
    left = np.full((32, 64, 3), 12, np.uint8)
    model = StartEcho()
    model.inference_config = InferenceConfig(coarse_start=True)
    np.testing.assert_allclose(infer(model, left, left), 24.0, rtol=1e-6)
    model.inference_config = InferenceConfig()
    np.testing.assert_allclose(infer(model, left, left), 12.0, rtol=1e-6)
    # a pair that needs padding: the coarse start is taken from the padded pair (replicate: still red 12), 32 x 64,
    # whose half is 16 x 32: the start is R x 64 / 32 px, everywhere
    odd = np.full((30, 61, 3), 12, np.uint8)
    model.inference_config = InferenceConfig(coarse_start=True)
    np.testing.assert_allclose(infer(model, odd, odd), 24.0, rtol=1e-5)


def test_trainer_draw(tmp_path: Path) -> None:
    # cascade_p 0: never a start; 1: always, on the batch's 1/8 grid; the draw repeats for the same (seed, step)
    from optstereo.training.config import TrainConfig
    from optstereo.training.loop import cascade_init

    torch.manual_seed(0)
    model = build_model("optstereo", **TINY, iters=2)
    left = torch.rand(2, 3, 64, 128) * 255
    state = SimpleNamespace(model=model, step=3)
    device = torch.device("cpu")
    assert cascade_init(state, TrainConfig(), device, left, left) is None
    always = TrainConfig.from_layers({"data": {"cascade_p": 1.0}})
    assert cascade_init(state, always, device, left, left).shape == (2, 1, 8, 16)
    half = TrainConfig.from_layers({"data": {"cascade_p": 0.5}})
    draws = [cascade_init(SimpleNamespace(model=model, step=k), half, device, left, left) is None for k in range(40)]
    again = [cascade_init(SimpleNamespace(model=model, step=k), half, device, left, left) is None for k in range(40)]
    assert draws == again and 5 < sum(draws) < 35
    with pytest.raises(Exception, match="cascade-p must be in"):
        TrainConfig.from_layers({"data": {"cascade_p": 1.5}})


def test_onnx_cascade_graph_matches_infer(tmp_path: Path, shared_data: Path) -> None:
    # a cascade model exports a graph with a third input, the start; infer_onnx runs the coarse pass and the final
    # one from it as infer does: the two agree at the export tests' tolerance, and differ from the zero start

    from optstereo.export import export, infer_onnx, onnx_inference_config, onnx_session

    torch.manual_seed(0)
    model = build_model("optstereo", **{**TINY, "iters": 3}).eval()
    model.inference_config = InferenceConfig(coarse_start=True, select=True, select_jump=0.02)
    session = onnx_session(export(model, tmp_path / "cascade.onnx"))
    assert [i.name for i in session.get_inputs()] == ["left", "right", "start"]
    assert onnx_inference_config(session) == InferenceConfig(coarse_start=True, select=True, select_jump=0.02,
                                                             iters=None)
    left, right = kitti_crop(shared_data, 96, 203)  # padding needed: the start is padded like the pair
    ref, got = infer(model, left, right), infer_onnx(session, left, right)
    diff = np.abs(got - ref)
    assert diff.mean() <= 0.01 and diff.max() <= 0.1, (diff.mean(), diff.max())
    plain = build_model("optstereo", **{**TINY, "iters": 3}).eval()
    plain.load_state_dict(model.state_dict())
    assert not np.allclose(ref, infer(plain, left, right), atol=0.1)  # the start changed the answer


def _shifted_pair(shift: int, h: int = 40, w: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """A textured (H, W, 3) uint8 pair whose true disparity is ``shift`` everywhere: left(x) = right(x - shift)."""
    rng = np.random.default_rng(0)
    right = rng.integers(0, 256, (h, w + shift, 3)).astype(np.uint8)
    right = (right.astype(np.float32) * 0.5 + np.roll(right, 1, axis=1) * 0.5).astype(np.uint8)  # some correlation
    return right[:, :w].copy(), right[:, shift:shift + w].copy()  # left(x) = wide(x), right(x) = wide(x + shift)


class TestPhotometricSelect:
    def test_keeps_the_true_disparity(self) -> None:
        left, right = _shifted_pair(5)
        true, wrong = np.full(left.shape[:2], 5.0, np.float32), np.full(left.shape[:2], 2.0, np.float32)
        for order in ((wrong, true), (true, wrong)):
            got = photometric_select(left, right, order)
            assert np.all(got[:, 12:] == 5.0)  # away from the left border, where a shift of 5 leaves the image

    def test_per_pixel(self) -> None:
        # each candidate is right on one half: the choice follows the halves, away from the seam (the box window)
        left, right = _shifted_pair(5)
        a, b = np.full(left.shape[:2], 5.0, np.float32), np.full(left.shape[:2], 5.0, np.float32)
        a[:, 48:], b[:, :48] = 9.0, 1.0
        got = photometric_select(left, right, (a, b))
        assert np.all(got[:, 12:42] == 5.0) and np.all(got[:, 54:] == 5.0)

    def test_one_answer_comes_back(self) -> None:
        left, right = _shifted_pair(5)
        ramp = np.tile(np.linspace(0.0, 8.0, left.shape[1], dtype=np.float32), (left.shape[0], 1))
        np.testing.assert_array_equal(photometric_select(left, right, (ramp,)), ramp)
        np.testing.assert_array_equal(photometric_select(left, right, (ramp, ramp.copy())), ramp)

    def test_jump_limit(self) -> None:
        # the zero start (second) is the true 5 px, the coarse start (first) a wrong 2 px, 3 px away: a limit of 3
        # px keeps the choice as it was, one of 2.9 px keeps the coarse start everywhere
        left, right = _shifted_pair(5)
        coarse, zero = np.full(left.shape[:2], 2.0, np.float32), np.full(left.shape[:2], 5.0, np.float32)
        assert np.all(photometric_select(left, right, (coarse, zero), max_jump=3.0)[:, 12:] == 5.0)
        np.testing.assert_array_equal(photometric_select(left, right, (coarse, zero), max_jump=2.9), coarse)

    def test_shapes_checked(self) -> None:
        left, right = _shifted_pair(5)
        with pytest.raises(ValueError, match="every candidate"):
            photometric_select(left, right, (np.zeros((4, 4), np.float32),))
        with pytest.raises(ValueError, match="every candidate"):
            photometric_select(left, right, (np.zeros(left.shape[:2], np.float32), np.zeros((4, 4), np.float32)))
        with pytest.raises(ValueError, match="at least one"):
            photometric_select(left, right, ())


def test_choose_by_hand() -> None:
    # costs favour the second candidate everywhere but the last pixel (a tie: the first); the jumps from the first
    # are 1, 5, 20, 20, 0 px
    disps = np.array([[[0.0, 0.0, 0.0, 0.0, 3.0]], [[1.0, 5.0, 20.0, -20.0, 3.0]]], np.float32)
    costs = np.array([[[0.5, 0.5, 0.5, 0.5, 0.2]], [[0.1, 0.1, 0.1, 0.1, 0.2]]], np.float32)
    np.testing.assert_array_equal(choose(disps, costs), [[1.0, 5.0, 20.0, -20.0, 3.0]])
    np.testing.assert_array_equal(choose(disps, costs, max_jump=5.0), [[1.0, 5.0, 0.0, 0.0, 3.0]])
    np.testing.assert_array_equal(choose(disps, costs, max_jump=4.99), [[1.0, 0.0, 0.0, 0.0, 3.0]])
    assert np.all(costs[1, 0, :4] == 0.1)  # the caller's costs are left as they were
    assert jump_limit(1242, 0.01) == pytest.approx(12.42) and jump_limit(1242, 0.0) == 0.0
    with pytest.raises(ValueError, match="select_jump"):
        jump_limit(100, -0.1)
    with pytest.raises(ValueError, match="select_jump needs select"):
        InferenceConfig(coarse_start=True, select_jump=0.01).validate()
    with pytest.raises(ValueError, match="select_jump must be a finite number"):
        InferenceConfig(coarse_start=True, select=True, select_jump=float("inf")).validate()



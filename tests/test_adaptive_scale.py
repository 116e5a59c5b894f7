"""The disparity-adaptive input scale: the rule by hand (optstereo.inference.rescale.adaptive_factor), the second pass
of
``run`` with a fake network whose output is known, the InferenceConfig, the checkpoint and the ONNX file."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY, Echo, kitti_crop

from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import first_scale, infer, model_inference_config, run
from optstereo.inference.rescale import ADAPTIVE_MIN_GAIN, ADAPTIVE_PERCENTILE, adaptive_factor, budget_factor
from optstereo.models import build_model

pytestmark = pytest.mark.usefixtures("one_torch_thread")


class TestRule:
    def test_hand_computed_factors(self) -> None:
        disp = np.full((100, 200), 10.0, np.float32)  # 20,000 px, p95 = 10 px
        # the disparity asks for 4x, the pixel cap allows sqrt(80,000 / 20,000) = 2x
        assert adaptive_factor(disp, ref_disp=40.0, ref_pixels=80_000) == pytest.approx(2.0)
        # the disparity asks for 1.5x, inside the cap
        assert adaptive_factor(disp, ref_disp=15.0, ref_pixels=80_000) == pytest.approx(1.5)
        # 1.05x is below ADAPTIVE_MIN_GAIN (1.1): no second pass
        assert ADAPTIVE_MIN_GAIN == 1.1
        assert adaptive_factor(disp, ref_disp=10.5, ref_pixels=80_000) == 1.0
        # never a shrink: disparities larger than the reference, or a pair as large as the training pairs
        assert adaptive_factor(disp, ref_disp=5.0, ref_pixels=80_000) == 1.0
        assert adaptive_factor(disp, ref_disp=40.0, ref_pixels=20_000) == 1.0

    def test_the_statistic_is_the_95th_percentile(self) -> None:
        # 0..99 px over 100 columns: numpy's linear percentile at 95 is 94.05 px; so ref 188.1 asks for exactly 2x
        disp = np.tile(np.arange(100, dtype=np.float32), (10, 1))
        assert ADAPTIVE_PERCENTILE == 95.0
        assert adaptive_factor(disp, ref_disp=188.1, ref_pixels=100_000) == pytest.approx(2.0)
        # NaN pixels are left out, not counted as zeros
        # (the odd columns remain: 1, 3, ..., 99, ten of each; 0.95 * 499 = 474.05 falls between two 95s -> 95 px;
        # zeros in their place would give 94.05)
        disp[:, ::2] = np.nan
        assert adaptive_factor(disp, ref_disp=190.0, ref_pixels=100_000) == pytest.approx(2.0)

    def test_no_positive_disparity_takes_the_pixel_cap(self) -> None:
        disp = np.zeros((10, 10), np.float32)
        assert adaptive_factor(disp, ref_disp=30.0, ref_pixels=900) == pytest.approx(3.0)
        assert adaptive_factor(np.full((10, 10), np.nan, np.float32), 30.0, 900) == pytest.approx(3.0)

    def test_counted_from_an_enlarged_first_pass(self) -> None:
        # the first pass ran 1.5x: its 10 px (input pixels) were 15 px there, its 20,000 px were 45,000: min(40 / 15,
        # sqrt(80,000 / 45,000)) = 4 / 3
        disp = np.full((100, 200), 10.0, np.float32)
        assert adaptive_factor(disp, ref_disp=40.0, ref_pixels=80_000, prior=1.5) == pytest.approx(4 / 3)

    def test_pixel_budget_by_hand(self) -> None:
        shape = (100, 200, 3)  # 20,000 px against a budget of 80,000: sqrt(4) = 2x
        assert budget_factor(shape, 80_000, cap=4.0) == pytest.approx(2.0)
        assert budget_factor(shape, 80_000, cap=1.5) == pytest.approx(1.5)  # the cap
        assert budget_factor(shape, 80_000, cap=1.0) == 1.0  # off
        assert budget_factor(shape, 80_000, cap=4.0, scale=2.0) == 1.0  # already at the budget
        assert budget_factor(shape, 22_000, cap=4.0) == 1.0  # sqrt(1.1) = 1.049 < ADAPTIVE_MIN_GAIN
        assert budget_factor(shape, 10_000, cap=4.0) == 1.0  # never a shrink
        with pytest.raises(ValueError, match="positive reference"):
            budget_factor(shape, 0, cap=2.0)

    def test_kitti_frames_are_never_enlarged(self) -> None:
        # version 15's reference (465,750 px) against the KITTI sizes of ../shared: all within 1.1x, so scale 1
        config = InferenceConfig(adaptive_ref_disp=60.1, adaptive_ref_pixels=465_750, enlarge_max=4.0)
        for shape in [(375, 1242), (376, 1241), (370, 1224), (370, 1226), (374, 1238)]:
            assert first_scale(config, shape) == 1.0, shape
        assert first_scale(config, (400, 881)) == pytest.approx(math.sqrt(465_750 / (400 * 881)))
        assert first_scale(config.replace(enlarge_max=1.25), (288, 384)) == 1.25

    def test_scale_and_budget_take_the_larger(self) -> None:
        """T8: with a budget, a pair runs at the larger of ``scale`` and the budget's enlargement of it as given; a
        budget factor under 1.1 counts as none (1), so it never drags a pair below ``scale``."""
        config = InferenceConfig(scale=1.0625, adaptive_ref_pixels=465_750, enlarge_max=4.0)
        assert first_scale(config, (375, 1242)) == 1.0625  # a KITTI frame: no budget enlargement
        driving = math.sqrt(465_750 / (400 * 881))  # 1.150: over the 1.1 threshold
        assert first_scale(config, (400, 881)) == pytest.approx(driving)
        assert first_scale(config, (360, 1200)) == 1.0625  # budget factor 1.037 < 1.1: none
        assert first_scale(config.replace(scale=1.25), (400, 881)) == 1.25
        assert first_scale(config.replace(enlarge_max=1.0), (288, 384)) == 1.0625  # no budget: scale alone

    def test_shrink_large_caps_the_pixels_at_a_training_pairs_at_scale(self) -> None:
        """T12: with ``shrink_large`` a pair of over 1.21x ``adaptive_ref_pixels`` pixels runs at scale x sqrt(ref /
        (H W)), so its first pass has ref x scale^2 pixels, as a training-size pair's; smaller pairs, and pairs
        within 1.1x per side of the reference (as the budget's enlargement leaves them), are unchanged."""
        config = InferenceConfig(scale=1.125, adaptive_ref_pixels=465_750, enlarge_max=4.0, shrink_large=True)
        room = first_scale(config, (860, 1080))  # an InStereo2K room: 1.125 x sqrt(465750 / 928800) = 0.797
        assert room == pytest.approx(1.125 * math.sqrt(465_750 / (860 * 1080)))
        assert 860 * 1080 * room**2 == pytest.approx(465_750 * 1.125**2)
        assert first_scale(config, (540, 960)) == 1.125  # FlyingThings3D: 0.948 per side, within 1.1: as before
        assert first_scale(config, (375, 1242)) == 1.125  # a KITTI frame: the reference itself
        assert first_scale(config, (376, 1241)) == 1.125  # KITTI 2012's 000070: 866 pixels over, left alone
        assert first_scale(config, (600, 1000)) == pytest.approx(1.125 * math.sqrt(465_750 / 600_000))  # 0.881
        assert first_scale(config, (400, 881)) == pytest.approx(math.sqrt(465_750 / (400 * 881)))  # budget as before
        assert first_scale(config.replace(shrink_large=False), (860, 1080)) == 1.125
        with pytest.raises(ValueError, match="shrink_large needs adaptive_ref_pixels"):
            InferenceConfig(shrink_large=True).validate()
        with pytest.raises(ValueError, match="shrink_large must be true or false"):
            InferenceConfig(shrink_large=1, adaptive_ref_pixels=10).validate()
        assert config.fixed(1.0).shrink_large is False  # a given scale is final

    def test_references_must_be_positive(self) -> None:
        with pytest.raises(ValueError, match="positive references"):
            adaptive_factor(np.ones((4, 4), np.float32), ref_disp=0.0, ref_pixels=10)


class TestInfer:
    @staticmethod
    def echo(**config: float) -> Echo:
        model = Echo()
        model.inference_config = InferenceConfig(**config)
        return model

    def test_second_pass_runs_at_the_factor(self) -> None:
        # Echo returns the red channel in pixels of the image it sees: red 10 is 10 px at scale 1 (the first pass),
        # so the rule asks min(40 / 10, sqrt(4 * 40 * 80 / (40 * 80))) = 2x, and the second pass at scale 2 returns
        # 10 px of the doubled pair = 5 px of the input (hand-computed).
        left = np.full((40, 80, 3), 10, np.uint8)
        model = self.echo(adaptive_ref_disp=40.0, adaptive_ref_pixels=4 * 40 * 80)
        result = run(model, left, left)
        assert result.input_scale == pytest.approx(2.0)
        np.testing.assert_allclose(result.disparity, 5.0, rtol=1e-5)
        np.testing.assert_array_equal(infer(model, left, left), result.disparity)

    def test_large_disparities_keep_one_pass(self) -> None:
        left = np.full((40, 80, 3), 50, np.uint8)  # 50 px > the reference 40 px: no enlargement
        result = run(self.echo(adaptive_ref_disp=40.0, adaptive_ref_pixels=4 * 40 * 80), left, left)
        assert result.input_scale == 1.0
        np.testing.assert_allclose(result.disparity, 50.0, rtol=1e-6)

    def test_first_pass_enlarged_by_the_pixel_budget(self) -> None:
        # a 40x80 pair against a budget of 4x its pixels (2x per side), capped at 1.5: the first pass at 1.5 sees
        # red 10 as 10 px of the enlarged pair = 10 / 1.5 px of the input; with no adaptive pass it is final
        left = np.full((40, 80, 3), 10, np.uint8)
        result = run(self.echo(adaptive_ref_pixels=4 * 40 * 80, enlarge_max=1.5), left, left)
        assert result.input_scale == pytest.approx(1.5)
        np.testing.assert_allclose(result.disparity, 10 / 1.5, rtol=1e-5)
        # with the adaptive pass, its factor is counted from 1.5: min(40 / (6.667 * 1.5), 2 / 1.5) -> 2x in all,
        # the scale the adaptive pass alone reaches (test_second_pass_runs_at_the_factor): never past the budget
        result = run(self.echo(adaptive_ref_disp=40.0, adaptive_ref_pixels=4 * 40 * 80, enlarge_max=1.5), left, left)
        assert result.input_scale == pytest.approx(2.0)
        np.testing.assert_allclose(result.disparity, 5.0, rtol=1e-5)
        # no cap: one pass at the budget, where the adaptive pass has nothing left to add
        result = run(self.echo(adaptive_ref_disp=40.0, adaptive_ref_pixels=4 * 40 * 80, enlarge_max=4.0), left, left)
        assert result.input_scale == pytest.approx(2.0)

    def test_large_pair_shrunk_by_the_pixel_cap(self) -> None:
        # T12: an 80x160 pair against a reference of a quarter of its pixels at scale 1.5: the pass runs at
        # 1.5 x 0.5 = 0.75 (40 x 60 x 1.5^2 pixels); red 12 is 12 px of the shrunk pair = 16 px of the input
        left = np.full((80, 160, 3), 12, np.uint8)
        model = self.echo(scale=1.5, adaptive_ref_pixels=80 * 160 // 4, shrink_large=True)
        result = run(model, left, left)
        assert result.input_scale == pytest.approx(0.75)
        np.testing.assert_allclose(result.disparity, 12 / 0.75, rtol=1e-5)
        assert run(model, left, left, model_inference_config(model, scale=1.5)).input_scale == 1.5  # given: final

    def test_a_given_scale_and_a_model_without_references_are_fixed(self) -> None:
        left = np.full((40, 80, 3), 10, np.uint8)
        model = self.echo(adaptive_ref_disp=40.0, adaptive_ref_pixels=4 * 40 * 80)
        fixed = run(model, left, left, model_inference_config(model, scale=1.0))
        assert fixed.input_scale == 1.0  # the caller's scale is final
        assert run(model, left, left, model_inference_config(model, scale=1.5)).input_scale == 1.5
        assert run(self.echo(), left, left).input_scale == 1.0  # no references: one pass
        budget = self.echo(adaptive_ref_pixels=4 * 40 * 80, enlarge_max=2.0)
        assert run(budget, left, left, model_inference_config(budget, scale=1.0)).input_scale == 1.0


class TestConfig:
    def test_validated(self) -> None:
        with pytest.raises(ValueError, match="needs adaptive_ref_pixels"):
            InferenceConfig(adaptive_ref_disp=60.0).validate()
        with pytest.raises(ValueError, match="adaptive_ref_disp must be >= 0"):
            InferenceConfig(adaptive_ref_disp=-1.0, adaptive_ref_pixels=10).validate()
        with pytest.raises(ValueError, match="adaptive_ref_disp must be a finite number"):
            InferenceConfig(adaptive_ref_disp=math.inf, adaptive_ref_pixels=10).validate()
        with pytest.raises(ValueError, match="enlarge_max needs adaptive_ref_pixels"):
            InferenceConfig(enlarge_max=1.5).validate()
        with pytest.raises(ValueError, match="enlarge_max must be >= 1"):
            InferenceConfig(enlarge_max=0.5, adaptive_ref_pixels=10).validate()
        fixed = InferenceConfig(adaptive_ref_disp=60.0, adaptive_ref_pixels=10, enlarge_max=2.0).fixed(1.25)
        assert (fixed.scale, fixed.adaptive, fixed.enlarge_max) == (1.25, False, 1.0)

    def test_survives_the_checkpoint(self, tmp_path: Path) -> None:
        from optstereo.api import load_model
        from optstereo.checkpoint import export_safetensors

        model = build_model("optstereo", **TINY, iters=2)
        refs = InferenceConfig(adaptive_ref_disp=61.5, adaptive_ref_pixels=465_750, enlarge_max=1.25)
        loaded = load_model(export_safetensors(tmp_path / "m.safetensors", model, inference=refs))
        assert loaded.inference_config == refs
        plain = load_model(export_safetensors(tmp_path / "p.safetensors", build_model("optstereo", **TINY, iters=2)))
        assert not plain.inference_config.adaptive  # the default: off


def test_onnx_file_records_the_references(tmp_path: Path, shared_data: Path) -> None:
    # The references travel in the ONNX metadata and infer_onnx runs the same second pass as infer: a reference
    # disparity far above any output and a pixel cap of 4x the pair's pixels make both enlarge by exactly 2x.

    from optstereo.export import export, infer_onnx, onnx_session

    torch.manual_seed(0)
    model = build_model("optstereo", **{**TINY, "iters": 3}).eval()
    model.inference_config = InferenceConfig(adaptive_ref_disp=1e6, adaptive_ref_pixels=4 * 64 * 120)
    session = onnx_session(export(model, tmp_path / "adaptive.onnx"))
    meta = json.loads(session.get_modelmeta().custom_metadata_map["inference_config"])
    assert meta["adaptive_ref_disp"] == 1e6 and meta["adaptive_ref_pixels"] == 4 * 64 * 120
    left, right = kitti_crop(shared_data, 64, 120)
    assert run(model, left, right).input_scale == pytest.approx(2.0)
    ref, got = infer(model, left, right), infer_onnx(session, left, right)
    assert not np.allclose(ref, infer(model, left, right, scale=1.0), atol=0.1)  # the second pass changed it
    diff = np.abs(got - ref)
    assert diff.mean() <= 0.01 and diff.max() <= 0.1, (diff.mean(), diff.max())


def test_final_scale_by_hand() -> None:
    """final_scale: the file's scale without the adaptive pass (no disparity needed); with it, that scale times the
    enlargement of the zero-start pass (a 20x30 map of 5 px against references 20 px / 2400 pixels: min(20 / 5,
    sqrt(2400 / 600)) = 2)."""
    from optstereo.inference.engine import final_scale

    assert final_scale(InferenceConfig(scale=1.25), None, (20, 30)) == 1.25
    adaptive = InferenceConfig(scale=1.5, adaptive_ref_disp=20.0, adaptive_ref_pixels=2400)
    assert final_scale(adaptive, np.full((20, 30), 5.0, np.float32), (20, 30)) == pytest.approx(3.0)
    with pytest.raises(ValueError, match="zero-start pass"):
        final_scale(adaptive, None, (20, 30))
    # the pixel budget alone (2x for 600 of 2400 px, capped at 1.5), on top of the file's scale 1
    assert final_scale(InferenceConfig(adaptive_ref_pixels=2400, enlarge_max=1.5), None, (20, 30)) == 1.5

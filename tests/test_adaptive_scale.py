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
from optstereo.inference.engine import infer, model_inference_config, run
from optstereo.inference.rescale import ADAPTIVE_MIN_GAIN, ADAPTIVE_PERCENTILE, adaptive_factor
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

    def test_a_given_scale_and_a_model_without_references_are_fixed(self) -> None:
        left = np.full((40, 80, 3), 10, np.uint8)
        model = self.echo(adaptive_ref_disp=40.0, adaptive_ref_pixels=4 * 40 * 80)
        fixed = run(model, left, left, model_inference_config(model, scale=1.0))
        assert fixed.input_scale == 1.0  # the caller's scale is final
        assert run(model, left, left, model_inference_config(model, scale=1.5)).input_scale == 1.5
        assert run(self.echo(), left, left).input_scale == 1.0  # no references: one pass


class TestConfig:
    def test_validated(self) -> None:
        with pytest.raises(ValueError, match="needs adaptive_ref_pixels"):
            InferenceConfig(adaptive_ref_disp=60.0).validate()
        with pytest.raises(ValueError, match="adaptive_ref_disp must be >= 0"):
            InferenceConfig(adaptive_ref_disp=-1.0, adaptive_ref_pixels=10).validate()
        with pytest.raises(ValueError, match="adaptive_ref_disp must be a finite number"):
            InferenceConfig(adaptive_ref_disp=math.inf, adaptive_ref_pixels=10).validate()

    def test_survives_the_checkpoint(self, tmp_path: Path) -> None:
        from optstereo.api import load_model
        from optstereo.checkpoint import export_safetensors

        model = build_model("optstereo", **TINY, iters=2)
        refs = InferenceConfig(adaptive_ref_disp=61.5, adaptive_ref_pixels=465_750)
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

    assert final_scale(InferenceConfig(scale=1.25), None) == 1.25
    adaptive = InferenceConfig(scale=1.5, adaptive_ref_disp=20.0, adaptive_ref_pixels=2400)
    assert final_scale(adaptive, np.full((20, 30), 5.0, np.float32)) == pytest.approx(3.0)
    with pytest.raises(ValueError, match="zero-start pass"):
        final_scale(adaptive, None)

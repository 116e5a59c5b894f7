"""Resizing a pair and its disparities by one factor (optstereo.inference.rescale): inference --scale and the training's
spatial scale augmentation --scale-range. Hand-computed maps, and a synthetic pair whose scaled label must still
match its scaled images."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from optstereo.cli import train_main
from optstereo.data.transforms import TrainTransform, crop_window, rescale_sample
from optstereo.inference.rescale import scaled_size, sparse_to_size
from optstereo.training.config import TrainConfig
from optstereo.training.sections import parse_scale_range
from pvm_labeler.common.errors import ConfigError

NAN = np.float32(np.nan)


def shifted_pair(height: int = 48, width: int = 96, d: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A smooth texture and its view shifted by ``d`` px: left(x) = right(x - d) everywhere, exactly."""
    y, x = np.mgrid[0:height, 0:width + d].astype(np.float32)
    tex = 128 + 50 * np.sin(2 * np.pi * x / 23) + 40 * np.cos(2 * np.pi * (x / 37 + y / 19)) + 20 * np.sin(y / 5)
    img = np.repeat(np.clip(tex, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    return np.ascontiguousarray(img[:, :width]), np.ascontiguousarray(img[:, d:])  # right(u) = left(u + d)


def test_sparse_to_size_hand_computed() -> None:
    label = np.array([[1, NAN, 3, 4], [NAN, 2, 2, NAN]], np.float32)
    up = sparse_to_size(label, (4, 8))  # x2 in each direction: every pixel becomes a 2x2 block, values x2
    np.testing.assert_array_equal(up, 2 * np.kron(label, np.ones((2, 2), np.float32)))
    np.testing.assert_array_equal(sparse_to_size(label, (4, 8), scale_values=False),
                                  np.kron(label, np.ones((2, 2), np.float32)))
    assert scaled_size((375, 1242, 3), 1.125) == (422, 1397) and scaled_size((10, 10), 0.1) == (8, 8)


@pytest.mark.parametrize(("width", "first_far"), [(100, 51), (40, 20)])
def test_sparse_to_size_keeps_pixel_centres(width: int, first_far: int) -> None:
    # A label step at column 41 of 80. Output column j samples the input at its centre, (j + 0.5) * 80 / width:
    # the first column at or past 41 is j = 51 at x1.25 (50.75 rounded up) and j = 20 at x0.5 (exactly 41). The
    # floor(j * 80 / width) convention of INTER_NEAREST would give 52 and 21: half a pixel off the images.
    label = np.where(np.arange(80) < 41, 1.0, 2.0).astype(np.float32)[None].repeat(4, 0)
    out = sparse_to_size(label, (4, width), scale_values=False)
    assert np.argmax(out[0] == 2.0) == first_far and np.all(out[:, :first_far] == 1.0)
    with pytest.raises(ValueError, match="scale must be positive"):
        scaled_size((10, 10), -1.0)


@pytest.mark.parametrize("scale", [1.5, 0.75])
def test_feature_scaled_label_still_matches_the_scaled_pair(scale: float) -> None:
    left, right = shifted_pair(d=4)
    label = np.full(left.shape[:2], 4.0, np.float32)
    label[10:20, 30:50] = NAN  # a hole
    weight = np.full(left.shape[:2], 0.5, np.float32)
    left_s, right_s, label_s, weight_s = rescale_sample(left, right, label, weight, scale)
    assert left_s.shape == right_s.shape == (*label_s.shape, 3) == (round(48 * scale), round(96 * scale), 3)
    d = 4 * scale  # 96 * scale is a whole number here, so the width ratio is exactly the scale
    np.testing.assert_allclose(label_s[np.isfinite(label_s)], d, rtol=1e-6)
    assert 0 < np.isnan(label_s).mean() < 0.1 and np.all(weight_s == 0.5)

    def warp_error(disp: float) -> float:
        """Mean |left(x) - right(x - disp)| over the interior (linear interpolation along the row)."""
        cols = np.arange(8, left_s.shape[1] - 8, dtype=np.float32)
        src = cols - disp
        lo = np.floor(src).astype(int)
        frac = src - lo
        r = right_s[..., 0].astype(np.float32)
        warped = r[:, lo] * (1 - frac) + r[:, lo + 1] * frac
        return float(np.abs(left_s[:, 8:-8, 0].astype(np.float32) - warped).mean())

    # The scaled label matches the scaled images to a grey level or so; the unscaled one (4 px) would not.
    assert warp_error(d) < 1.0 and warp_error(4.0) > 4.0, (warp_error(d), warp_error(4.0))


def test_transform_scale_range() -> None:
    left, right = shifted_pair(d=4)
    label = np.full(left.shape[:2], 4.0, np.float32)
    big = TrainTransform(crop=(512, 512), flip_swap_p=0.0, scale_range=(2.0, 2.0))
    left_s, _, label_s = big(left, right, label, None, np.random.default_rng(0))
    assert left_s.shape == (96, 192, 3) and np.all(label_s == 8.0)  # whole frame (smaller than the crop), x2
    # Off ((1, 1), also as a YAML list) draws nothing: after the flip draw, the next draw is the crop window.
    rng = np.random.default_rng(3)
    rng.random()
    y0, x0, h, w = crop_window(48, 96, (16, 32), rng)
    for off in ((1.0, 1.0), [1, 1]):
        got = TrainTransform(crop=(16, 32), flip_swap_p=0.0, scale_range=off)(
            left, right, label, None, np.random.default_rng(3))[0]
        np.testing.assert_array_equal(got, left[y0:y0 + h, x0:x0 + w])
    on = TrainTransform(crop=(16, 32), flip_swap_p=0.0, scale_range=(1.0, 1.001))  # one more draw: another window
    assert not np.array_equal(on(left, right, label, None, np.random.default_rng(3))[0], left[y0:y0 + h, x0:x0 + w])


def test_scale_range_config_and_flag(tmp_path: Path) -> None:
    assert parse_scale_range("1.0,1.25") == (1.0, 1.25) == parse_scale_range([1, 1.25])
    for bad in ("1.2", "a,b", "1.3,1.2", "0,1", "1,inf"):
        with pytest.raises(ConfigError, match="--scale-range"):
            parse_scale_range(bad)
    result = CliRunner().invoke(train_main, ["--scale-range", "1,1.25", "--print-config"])
    assert result.exit_code == 0, result.output
    printed = yaml.safe_load(result.output)
    assert printed["data"]["scale_range"] == [1.0, 1.25]
    assert TrainConfig.from_dict(printed).data.scale_range == (1.0, 1.25)  # a saved run's config reads back
    assert TrainConfig().data.scale_range == (1.0, 1.0)
    # The exports of a run on enlarged crops record the middle of the range as their input scale, unless set.
    assert printed["inference"]["scale"] == 1.125 and "input_scale" not in printed["model"]
    assert TrainConfig().inference.scale == 1.0
    own = TrainConfig.from_dict({"data": {"scale_range": [1.5, 1.75]}, "inference": {"scale": 1.5}})
    assert own.inference.scale == 1.5
    old = TrainConfig.from_dict({"data": {"scale_range": [1.5, 1.75]}, "model": {"input_scale": 1.5}})  # old YAML
    assert old.inference.scale == 1.5
    bad = CliRunner().invoke(train_main, ["--scale-range", "2,1", "--print-config"])
    assert bad.exit_code == 2 and "0 < LO <= HI" in bad.output

"""T11's study (pipelines/studies/downsize.py): the resizes by hand on a step and a ramp, the arms inside the
model's own ``run``, the registered rule on hand-made scores."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import Echo

from optstereo import validation
from optstereo.inference import engine
from optstereo.inference.config import InferenceConfig
from optstereo.inference.rescale import disparity_to_size
from pipelines.studies import downsize


def step(h: int = 9, w: int = 18, edge: int = 10, low: float = 10.0, high: float = 40.0) -> np.ndarray:
    disp = np.full((h, w), low, np.float32)
    disp[:, edge:] = high
    return disp


def test_nearest_keeps_only_the_sources_values() -> None:
    src = step()
    got = downsize.nearest_to_size(src, (6, 12))  # 2/3 of the size: values times 12 / 18
    assert got.shape == (6, 12)
    # by centres, output column j takes source column floor((j + 0.5) * 1.5): j = 6 -> 9 (left of the edge at 10),
    # j = 7 -> 11; bilinear samples x = (j + 0.5) * 1.5 - 0.5, j = 6 -> 9.25, between 9 and 10: a blend
    assert np.allclose(got[:, :7], 10.0 * 2 / 3) and np.allclose(got[:, 7:], 40.0 * 2 / 3)
    bilinear = disparity_to_size(src, (6, 12))
    assert ((bilinear > 10.0 * 2 / 3 + 1e-3) & (bilinear < 40.0 * 2 / 3 - 1e-3)).any()  # bilinear blends the edge


def test_hybrid_is_bilinear_on_a_ramp_and_nearest_at_a_step() -> None:
    ramp = np.tile(np.linspace(10.0, 20.0, 30, dtype=np.float32), (12, 1))  # 0.34 px per pixel: no edge
    np.testing.assert_array_equal(downsize.hybrid_to_size(ramp, (8, 20)), disparity_to_size(ramp, (8, 20)))
    src = step()
    got = downsize.hybrid_to_size(src, (6, 12))
    np.testing.assert_array_equal(got, downsize.nearest_to_size(src, (6, 12)))  # a blend of the edge is > tau off
    enlarge = downsize.hybrid_to_size(src, (18, 36))  # enlarging: the same rule, values times 2
    assert np.isin(np.round(enlarge, 4), np.round([20.0, 80.0], 4)).all()


def test_arms_replace_only_the_resize_back() -> None:
    model = Echo()
    model.inference_config = InferenceConfig(scale=1.5)
    rng = np.random.default_rng(0)
    left = rng.integers(0, 255, (24, 40, 3), dtype=np.uint8)
    right = left.copy()
    config = model.inference_config
    np.testing.assert_array_equal(downsize.predictor(model, "linear")(left, right),
                                  engine.run(model, left, right, config).disparity)
    near = downsize.predictor(model, "nearest")(left, right)
    assert engine.disparity_to_size is disparity_to_size  # the patch ends with the call
    left_s, right_s = engine.rescaled_pair(left, right, 1.5)
    np.testing.assert_allclose(near, downsize.nearest_to_size(left_s[..., 0].astype(np.float32), (24, 40)),
                               atol=1e-4)  # Echo's disparity is the red channel of the image it saw


def pairs(pvm: list[float], teacher: list[float], photo: float = 1.0) -> list[validation.PairScore]:
    return [validation.PairScore(f"p{i}", pvm_n=1, pvm_err=e, teacher_n=1, teacher_err=t, photo_sum=photo,
                                 photo_n=1) for i, (e, t) in enumerate(zip(pvm, teacher, strict=True))]


def test_rule_needs_a_gain_somewhere_and_no_loss_anywhere() -> None:
    base = pairs([1.0, 1.1, 0.9, 1.0], [2.0, 2.1, 1.9, 2.0])
    gain = pairs([0.9, 1.0, 0.8, 0.9], [2.0, 2.1, 1.9, 2.0])
    same = base
    worse_teacher = pairs([0.9, 1.0, 0.8, 0.9], [2.5, 2.6, 2.4, 2.5])
    val = {"linear": base, "nearest": same, "hybrid": gain}
    ku = {"linear": base, "nearest": gain, "hybrid": same}
    best, lines = downsize.decide(val, ku)
    assert best == "nearest" and lines[-1] == "candidate: nearest"  # both pass; the lower KITTI-domain PVM EPE
    assert downsize.decide({"linear": base, "nearest": same, "hybrid": same},
                           {"linear": base, "nearest": same, "hybrid": same})[0] is None  # no gain anywhere
    assert downsize.decide({"linear": base, "nearest": worse_teacher, "hybrid": same},
                           {"linear": base, "nearest": gain, "hybrid": same})[0] is None  # a loss on one set
    with pytest.raises(KeyError):
        downsize.decide({"linear": base}, ku)

"""T3's study (pipelines/studies/aspect.py): the sizes by hand, the disparity's units through a width-for-height
resize, a = 1 scoring exactly as ``optstereo-eval --valset`` does, the registered rule on hand-made scores."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import Echo, make_valset

from optstereo import validation
from optstereo.inference.config import InferenceConfig
from pipelines.studies import aspect


def echo(pixels: int = 4 * 32 * 64) -> Echo:
    model = Echo()
    model.inference_config = InferenceConfig(adaptive_ref_pixels=pixels)
    return model


def test_sizes_by_hand() -> None:
    assert aspect.aspect_size((375, 1242, 3), 1.0, 1.25) == (300, 1552)  # 375 / 1.25, 1242 * 1.25 = 1552.5 -> 1552
    assert aspect.aspect_size((375, 1242), 1.0, 1.0) == (375, 1242)
    assert aspect.aspect_size((100, 200), 2.0, 2.0) == (100, 800)
    assert aspect.aspect_size((10, 10), 1.0, 4.0) == (8, 40)  # at least 8 rows
    with pytest.raises(ValueError, match="positive"):
        aspect.aspect_size((10, 10), 1.0, 0.0)


def test_resize_each_axis_keeps_a_constant_image() -> None:
    image = np.full((30, 40, 3), 77, np.uint8)
    out = aspect.resize_image(image, (24, 50))
    assert out.shape == (24, 50, 3) and (out == 77).all()
    same = np.arange(30 * 40 * 3, dtype=np.uint8).reshape(30, 40, 3)
    assert aspect.resize_image(same, (30, 40)) is same


def test_iterations_reach_the_network() -> None:
    seen = []

    class Counting(Echo):
        def forward(self, left, right, iters=None, test_mode=False):  # type: ignore[override]
            seen.append(iters)
            return super().forward(left, right, iters, test_mode)

    model = Counting()
    model.inference_config = InferenceConfig()
    pair = np.zeros((16, 16, 3), np.uint8)
    aspect.aspect_predict(model, 1.0)(pair, pair)
    aspect.aspect_predict(model, 1.0, iters=10)(pair, pair)
    assert seen == [None, 10]


def test_disparity_comes_back_in_the_pairs_pixels() -> None:
    """Echo's disparity is the left image's red channel in the pixels it saw: 80 at twice the width is 40 in the
    pair's own pixels, everywhere (a constant image survives both resizes exactly)."""
    left = np.zeros((64, 96, 3), np.uint8)
    left[..., 0] = 80
    predict = aspect.aspect_predict(echo(pixels=1), 2.0)  # a 1-pixel budget: the first scale stays 1
    disp = predict(left, left.copy())
    assert disp.shape == (64, 96) and disp.dtype == np.float32
    np.testing.assert_allclose(disp, 40.0, atol=1e-4)


def test_aspect_one_scores_as_the_valset_does(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    root = make_valset(tmp_path / "val", teacher_digest="not-this-model")
    monkeypatch.setattr(aspect, "load_model", lambda name: echo())
    got = aspect.score_arms(root, [aspect.BASE], tmp_path / "out")[aspect.BASE]
    want = validation.score(echo(), validation.open_valset(root)).pairs
    assert [vars(p) for p in got] == [vars(p) for p in want]
    assert (tmp_path / "out" / "val_a1.json").exists()
    monkeypatch.setattr(aspect, "load_model", lambda name: pytest.fail("a scored arm is read back"))
    again = aspect.score_arms(root, [aspect.BASE], tmp_path / "out")[aspect.BASE]
    assert [vars(p) for p in again] == [vars(p) for p in want]


def pairs(pvm: list[float], teacher: list[float]) -> list[validation.PairScore]:
    return [validation.PairScore(f"p{i}", pvm_n=1, pvm_err=e, teacher_n=1, teacher_err=t, photo_sum=1.0, photo_n=1)
            for i, (e, t) in enumerate(zip(pvm, teacher, strict=True))]


def test_rule_takes_the_lowest_arm_only() -> None:
    base = pairs([1.0, 1.1, 0.9, 1.0], [2.0] * 4)
    better = pairs([0.9, 1.0, 0.8, 0.9], [2.0] * 4)  # -0.1 on every pair, teacher unchanged: a candidate
    lowest_but_off_teacher = pairs([0.8, 0.9, 0.7, 0.8], [2.5, 2.6, 2.4, 2.5])  # lower, but +0.5 teacher EPE
    a1, a2, n10 = aspect.BASE, aspect.Arm(1.125), aspect.Arm(1.0, 10)
    assert aspect.rule({a1: base, a2: better})[0] == a2
    assert aspect.rule({a1: base, a2: better, n10: lowest_but_off_teacher})[0] is None
    assert aspect.not_worse(base, better) and not aspect.not_worse(base, lowest_but_off_teacher)
    assert [a.name for a in (a1, a2, n10)] == ["a1", "a1.125", "a1_n10"]


def test_prefix_picks_pairs_by_id(tmp_path: Path) -> None:
    root = make_valset(tmp_path / "val", teacher_digest="not-this-model")
    ids = [p.frame_id for p in validation.score(echo(), validation.open_valset(root)).pairs]
    assert aspect.prefixed(root, "") is None
    assert aspect.prefixed(root, ids[0]) == {ids[0]}
    with pytest.raises(ValueError, match="no pair of .* starting with 'nothing-"):
        aspect.prefixed(root, "nothing-")


def test_config_arm_runs_the_models_own_path() -> None:
    """T7's arm is ``run`` with the model's settings changed (scale, iters, no adaptive pass): what would ship."""
    from optstereo.inference.engine import run

    model = echo(pixels=64 * 96)
    model.inference_config = InferenceConfig(adaptive_ref_disp=60.0, adaptive_ref_pixels=64 * 96, enlarge_max=4.0)
    changed = aspect.config_arm(model.inference_config, 1.125, 4)
    assert (changed.scale, changed.iters, changed.adaptive_ref_disp, changed.enlarge_max) == (1.125, 4, 0.0, 4.0)
    assert aspect.config_arm(model.inference_config, 1.0, None).iters is None
    rng = np.random.default_rng(0)
    left = rng.integers(0, 255, (40, 72, 3), dtype=np.uint8)
    got = aspect.arm_predict(model, aspect.Arm(1.0, 4, 1.125, config=True))(left, left.copy())
    np.testing.assert_array_equal(got, run(model, left, left.copy(), changed).disparity)
    assert aspect.Arm(1.0, 4, 1.125, config=True).name == "a1_n4_s1.125_cfg"
    with pytest.raises(ValueError, match="aspect 1"):
        aspect.arm_predict(model, aspect.Arm(1.25, 4, 1.125, config=True))

"""optstereo.inference.confidence: range and shape on a tiny model, the LR difference and the sparsification curve by
hand,
the files and the CLI's conf formats / --min-confidence."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY

from optstereo.inference.confidence import (
    METHODS,
    confidence_of,
    curve_area,
    infer_with_confidence,
    iteration_predictions,
    lr_difference,
    sparsification,
    write_confidence,
)
from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import infer
from optstereo.models import build_model
from pvm_labeler.common.io import write_image

pytestmark = pytest.mark.usefixtures("one_torch_thread")

def _tiny() -> torch.nn.Module:
    torch.manual_seed(0)
    model = build_model("optstereo", **TINY).eval()
    model.inference_config = InferenceConfig()
    return model


def _pair(seed: int = 0, shape: tuple[int, int] = (40, 100)) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return tuple(rng.integers(0, 256, (*shape, 3), dtype=np.uint8) for _ in range(2))


@pytest.mark.parametrize("method", METHODS)
def test_range_and_shape(method: str) -> None:
    model = _tiny()
    left, right = _pair()  # 40 x 100: padded to the model's multiple inside
    disp, conf = infer_with_confidence(model, left, right, method=method)
    np.testing.assert_array_equal(disp, infer(model, left, right))
    assert conf.shape == (40, 100) and conf.dtype == np.float32
    assert np.all(np.isfinite(conf)) and conf.min() >= 0 and conf.max() <= 1
    with pytest.raises(ValueError, match="confidence method"):
        confidence_of(model, left, right, disp, method="oracle")


def test_iteration_predictions_end_at_the_plain_pass() -> None:
    model = _tiny()
    left, right = _pair(1)
    preds = iteration_predictions(model, left, right, iters=3)
    assert preds.shape == (3, 40, 100)
    np.testing.assert_allclose(preds[-1], infer(model, left, right, iters=3), rtol=1e-5, atol=1e-4)


def test_lr_difference_by_hand() -> None:
    d_left = np.array([[0.0, 1.0, 2.5, 3.0, 9.0]], np.float32)
    d_right = np.array([[1.0, 2.0, 3.0, 4.0, 5.0]], np.float32)
    # x=0: at 0 -> |0 - 1| = 1; x=1: at 0 -> 0; x=2: at -0.5 outside -> inf; x=3: at 0 -> |3 - 1| = 2; x=4: outside
    np.testing.assert_allclose(lr_difference(d_left, d_right), [[1.0, 0.0, np.inf, 2.0, np.inf]])
    d_left = np.array([[0.0, 0.0, 0.5, 0.0]], np.float32)  # x=2 at 1.5: between 2 and 3 -> 2.5, |0.5 - 2.5| = 2
    np.testing.assert_allclose(lr_difference(d_left, d_right)[0, 2], 2.0)


def test_sparsification_by_hand() -> None:
    conf = np.array([0.9, 0.8, 0.7, 0.6])
    err = np.array([0.0, 5.0, 0.0, 5.0])
    dens = (0.25, 0.5, 0.75, 1.0)
    np.testing.assert_allclose(sparsification(conf, err, dens), [0.0, 50.0, 100 / 3, 50.0])
    np.testing.assert_allclose(sparsification(-err, err, dens), [0.0, 0.0, 100 / 3, 50.0])  # the oracle
    np.testing.assert_allclose(sparsification(np.zeros(4), err, dens), [0.0, 50.0, 100 / 3, 50.0])  # stable ties
    # trapezoids over 0.25..1: (0+50)/2*.25 + (50+33.3)/2*.25 + (33.3+50)/2*.25
    assert curve_area(sparsification(conf, err, dens), dens) == pytest.approx(0.25 * (25 + 250 / 6 + 250 / 6))
    with pytest.raises(ValueError, match="equal non-empty"):
        sparsification(conf, err[:2])


def test_confidence_files(tmp_path: Path) -> None:
    conf = np.array([[0.0, 0.5], [1.0, 0.25]], np.float32)
    paths = write_confidence(tmp_path, "f", conf, ["conf-png", "conf-npy"])
    png = cv2.imread(str(paths["conf-png"]), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16
    np.testing.assert_array_equal(png, [[0, 32768], [65535, 16384]])
    np.testing.assert_array_equal(np.load(paths["conf-npy"]), conf)


def test_predict_cli_conf_formats_and_min_confidence(tmp_path: Path) -> None:
    from optstereo.checkpoint import save_checkpoint
    from optstereo.cli import predict_main

    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", model=build_model("optstereo", **TINY), step=0)
    left, right = _pair(2, (64, 128))
    write_image(tmp_path / "l.png", left)
    write_image(tmp_path / "r.png", right)
    args = ["--checkpoint", str(ckpt), str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--device", "cpu",
            "--refine", "none", "--quiet", "--format", "npy", "--format", "conf-npy", "--format", "conf-png"]
    res = CliRunner().invoke(predict_main, [*args, "--out", str(tmp_path / "dense")])
    assert res.exit_code == 0, res.output
    conf = np.load(tmp_path / "dense" / "l_conf.npy")
    dense = np.load(tmp_path / "dense" / "l.npy")
    assert conf.shape == dense.shape == (64, 128) and 0 <= conf.min() and conf.max() <= 1
    png = cv2.imread(str(tmp_path / "dense" / "l_conf.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(png / 65535, conf, atol=1 / 65535)
    cut = float(np.median(conf))
    res = CliRunner().invoke(predict_main, [*args, "--out", str(tmp_path / "semi"), "--min-confidence", str(cut)])
    assert res.exit_code == 0, res.output
    semi = np.load(tmp_path / "semi" / "l.npy")
    # two runs may time Winograd against direct GRU convolutions differently (float rounding, ~1e-6 px): compare to
    # 1e-4 and leave out pixels within 0.1 % of the cut (the tiny random network's confidences are ~1e-6)
    keep, drop = conf > cut * 1.001, conf < cut * 0.999
    np.testing.assert_allclose(semi[keep], dense[keep], atol=1e-4)
    assert np.all(np.isnan(semi[drop])) and 0 < keep.mean() < 1 and 0 < drop.mean() < 1



def test_predict_cli_confidence_pass_runs_at_the_disparity_pass_scale(tmp_path: Path) -> None:
    """With --scale 1.5 the mirrored LR pass of the written confidence runs at 1.5 too: the files equal
    infer_with_confidence's (it ran at 1 before, against a disparity made at 1.5)."""
    from optstereo.checkpoint import build_model_from_checkpoint, save_checkpoint
    from optstereo.cli import predict_main

    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", model=build_model("optstereo", **TINY), step=0)
    left, right = _pair(2, (64, 128))
    write_image(tmp_path / "l.png", left)
    write_image(tmp_path / "r.png", right)
    res = CliRunner().invoke(predict_main, ["--checkpoint", str(ckpt), str(tmp_path / "l.png"), str(tmp_path / "r.png"),
                                            "--device", "cpu", "--refine", "none", "--scale", "1.5", "--quiet",
                                            "--format", "npy", "--format", "conf-npy", "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    disp, conf = infer_with_confidence(build_model_from_checkpoint(ckpt), left, right, scale=1.5, refine="none")
    np.testing.assert_allclose(np.load(tmp_path / "o" / "l.npy"), disp, atol=1e-4)
    np.testing.assert_allclose(np.load(tmp_path / "o" / "l_conf.npy"), conf, atol=1e-4)

def test_lr_pass_runs_the_settings_iterations() -> None:
    """The mirrored pass of ``lr`` runs the GRU iterations of the pass that made the disparity (a file's
    InferenceConfig.iters, 3 in version 15 since T8), not the network's default (8): both views alike."""
    from optstereo.inference.confidence import lr_difference, right_view_disparity

    torch.manual_seed(0)
    model = build_model("optstereo", iters=6, **TINY).eval()
    model.inference_config = InferenceConfig(iters=2)
    left, right = _pair(4, (48, 96))
    disp, conf = infer_with_confidence(model, left, right, method="lr")
    want = np.exp(-lr_difference(disp, right_view_disparity(model, left, right, iters=2))).astype(np.float32)
    np.testing.assert_allclose(conf, want, atol=1e-6)
    default = np.exp(-lr_difference(disp, right_view_disparity(model, left, right))).astype(np.float32)
    assert not np.allclose(conf, default, atol=1e-3)  # the network's default iterations give another confidence


def test_api_predict_with_confidence() -> None:
    from optstereo.api import predict

    model = _tiny()
    left, right = _pair(3)
    disp, conf = predict(model, left, right, confidence=True)
    np.testing.assert_array_equal(disp, predict(model, left, right))
    assert conf.shape == disp.shape and 0 <= conf.min() and conf.max() <= 1
    (pair,) = predict(model, [(left, right)], confidence=True)
    np.testing.assert_array_equal(pair[1], conf)

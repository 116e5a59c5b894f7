"""optstereo-export: the ONNX graph run by onnxruntime matches torch on a real KITTI pair; TorchScript too."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY, kitti_crop

from optstereo.checkpoint import export_safetensors
from optstereo.cli import export_main, predict_main
from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import infer
from optstereo.models import build_model
from pvm_labeler.common.io import read_image, write_image

pytest.importorskip("onnxruntime")


@pytest.fixture(scope="module")
def export_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, subprocess.CompletedProcess]:
    """`optstereo-export` of a tiny model in a fresh process (the exporter warns once per process, so only a fresh
    one shows its chatter): the checkpoint, the .onnx file and the finished process (each export takes ~20 s:
    the tests share this one)."""
    root = tmp_path_factory.mktemp("export")
    torch.manual_seed(0)
    ckpt = export_safetensors(root / "tiny.safetensors", build_model("optstereo", iters=3, **TINY))
    done = subprocess.run([sys.executable, "-m", "optstereo.cli", "export", "--checkpoint", str(ckpt), "--out",
                           str(root / "tiny.onnx")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert sorted(p.name for p in root.iterdir() if "onnx" in p.name) == ["tiny.onnx"]  # weights inside, no side file
    return ckpt, root / "tiny.onnx", done


@pytest.fixture(scope="module")
def exported(export_run: tuple[Path, Path, subprocess.CompletedProcess]) -> tuple[Path, Path]:
    return export_run[0], export_run[1]


def test_onnxruntime_matches_torch_on_kitti(exported: tuple[Path, Path], shared_data: Path) -> None:
    from optstereo.api import load_model
    from optstereo.export import infer_onnx, onnx_session

    ckpt, onnx_file = exported
    model = load_model(ckpt)
    session = onnx_session(onnx_file)
    for h, w in ((128, 256), (141, 389)):  # dynamic size, and one that needs padding outside the graph
        left, right = kitti_crop(shared_data, h, w)
        ref = infer(model, left, right)
        got = infer_onnx(session, left, right)
        assert got.shape == (h, w)
        diff = np.abs(got - ref)
        assert diff.mean() <= 0.01 and diff.max() <= 0.1, (h, w, diff.mean(), diff.max())


def test_onnx_file_records_the_models_settings(tmp_path: Path, shared_data: Path) -> None:
    """A file's InferenceConfig travels into the export (one export of three settings: ~20 s each): an input
    scale (a model trained for enlarged inputs), by which infer_onnx resizes as infer does; GRU iterations (version
    15 since T8: 3, its network's default 6 here) in the metadata and the unrolled graph; the post-filter, which
    infer_onnx applies and refine= overrides. The two agree at the issue's tolerance."""
    from optstereo.export import export, infer_onnx, onnx_inference_config, onnx_session
    from pvm_labeler.refine import weighted_median

    torch.manual_seed(0)
    model = build_model("optstereo", iters=6, **TINY).eval()
    model.inference_config = InferenceConfig(scale=1.5, iters=2, refine="wmedian")
    session = onnx_session(export(model, tmp_path / "set.onnx"))
    recorded = onnx_inference_config(session)
    assert (recorded.scale, recorded.iters, recorded.refine) == (1.5, 2, "wmedian")
    left, right = kitti_crop(shared_data, 96, 200)
    ref, raw = infer(model, left, right, refine="none"), infer_onnx(session, left, right, refine="none")
    assert raw.shape == (96, 200)
    for plain in ({"scale": 1.0}, {"iters": 6}):  # each setting changes the output
        assert not np.allclose(ref, infer(model, left, right, refine="none", **plain), atol=1e-3), plain
    diff = np.abs(raw - ref)
    assert diff.mean() <= 0.01 and diff.max() <= 0.1, (diff.mean(), diff.max())
    np.testing.assert_array_equal(infer_onnx(session, left, right), weighted_median(raw, left))  # the file's filter
    # scale= overrides the file's, as it overrides the model's in infer
    diff = np.abs(infer_onnx(session, left, right, scale=1.0, refine="none")
                  - infer(model, left, right, scale=1.0, refine="none"))
    assert diff.mean() <= 0.01 and diff.max() <= 0.1, (diff.mean(), diff.max())


def test_predict_backend_onnxruntime(exported: tuple[Path, Path], shared_data: Path, tmp_path: Path) -> None:
    ckpt, onnx_file = exported
    base = shared_data / "kitti15/training"
    pair = [str(base / "image_2/000001_10.png"), str(base / "image_3/000001_10.png")]
    runs = {}
    for scale in ((), ("--scale", "0.5")):  # the file's own input scale, then another one, on both backends
        for backend, checkpoint in (("torch", ckpt), ("onnxruntime", onnx_file)):
            out = tmp_path / f"{backend}{len(scale)}"
            result = CliRunner().invoke(predict_main, ["--checkpoint", str(checkpoint), *pair, "--out", str(out),
                                                       "--format", "npy", "--backend", backend, *scale])
            assert result.exit_code == 0, result.output
            runs[backend, scale] = np.load(out / "000001_10.npy")
        diff = np.abs(runs["onnxruntime", scale] - runs["torch", scale])  # a full KITTI frame, padded to x8
        assert runs["torch", scale].shape == (375, 1242) and diff.mean() <= 0.01 and diff.max() <= 0.1, scale
    assert not np.allclose(runs["torch", ()], runs["torch", ("--scale", "0.5")], atol=0.1)  # the scale did act


def test_dynamic_batch_export(exported: tuple[Path, Path], tmp_path: Path, shared_data: Path) -> None:
    """--batch: a (2, 3, H, W) batch through onnxruntime equals torch per pair; the default graph takes batch 1."""
    from optstereo.export import export, onnx_session

    torch.manual_seed(0)
    model = build_model("optstereo", iters=2, **TINY).eval()
    session = onnx_session(export(model, tmp_path / "b.onnx", batch=True))
    pairs = [kitti_crop(shared_data, 64, 128), kitti_crop(shared_data, 64, 128)[::-1]]
    to_t = lambda x: np.ascontiguousarray(x.transpose(2, 0, 1)).astype(np.float32)  # noqa: E731
    left = np.stack([to_t(p[0]) for p in pairs])
    right = np.stack([to_t(p[1]) for p in pairs])
    out = session.run(["disparity"], {"left": left, "right": right})[0]
    for i, (lft, rgt) in enumerate(pairs):
        assert np.abs(out[i, 0] - infer(model, lft, rgt)).max() <= 0.1
    assert onnx_session(exported[1]).get_inputs()[0].shape[0] == 1  # the default export (no --batch)


def test_torchscript_export(exported: tuple[Path, Path], tmp_path: Path, shared_data: Path) -> None:
    ckpt, _ = exported
    result = CliRunner().invoke(export_main, ["--checkpoint", str(ckpt), "--format", "torchscript", "--out",
                                              str(tmp_path / "tiny.pt"), "--quiet"])
    assert result.exit_code == 0, result.output
    scripted = torch.jit.load(str(tmp_path / "tiny.pt"))
    to_t = lambda x: torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1))).float()[None]  # noqa: E731
    from optstereo.api import load_model

    model = load_model(ckpt)
    for h, w in ((64, 128), (128, 256)):  # traced at 64 x 128: does another size still run through the graph?
        left, right = kitti_crop(shared_data, h, w)
        with torch.no_grad():
            got = scripted(to_t(left), to_t(right))[0, 0].numpy()
        np.testing.assert_allclose(got, infer(model, left, right), atol=1e-3)
    extra = {"inference_config.json": ""}
    torch.jit.load(str(tmp_path / "tiny.pt"), _extra_files=extra)  # the settings travel with the graph
    assert json.loads(extra["inference_config.json"]) == model.inference_config.to_dict()
    for name, image in (("l.png", left), ("r.png", right)):
        write_image(tmp_path / name, image)
    refused = CliRunner().invoke(predict_main, ["--checkpoint", str(tmp_path / "tiny.pt"), str(tmp_path / "l.png"),
                                                str(tmp_path / "r.png"), "--out", str(tmp_path / "o")])
    # it was torch.load's advice to unpickle with weights_only=False
    assert refused.exit_code == 1 and "is an exported TorchScript graph" in refused.output, refused.output
    assert "weights_only" not in refused.output


@pytest.mark.slow
@pytest.mark.parametrize("name", ["pretrained", "pretrained-accurate"])
def test_shipped_model_onnx_at_kitti_size(tmp_path: Path, shared_data: Path, name: str) -> None:
    """The issue's bar: a shipped model, ONNX vs torch on a full KITTI frame, mean <= 0.01 px, max <= 0.1 px, for
    its network passes. The one-pass default (version 15) holds it end to end. Version 14's per-pixel choice between
    its two starts flips where their photometric costs tie to float precision (38 of 465,750 pixels on this frame,
    2026-11-27), so there the end-to-end bar is mean <= 0.01 px and at most 1 pixel in 2000 beyond 0.1 px."""
    from optstereo.api import load_model
    from optstereo.export import OnnxNetwork, export, infer_onnx, onnx_session
    from optstereo.inference.engine import run
    from optstereo.inference.fastpath import engineering

    model = load_model(name)
    session = onnx_session(export(model, tmp_path / "model.onnx"))
    base = shared_data / "kitti15/training"
    left, right = read_image(base / "image_2/000005_10.png"), read_image(base / "image_3/000005_10.png")
    with engineering(True, int8=False):  # the graph is float32: held to the float32 torch pass (int8: test_int8.py)
        end_to_end = np.abs(infer_onnx(session, left, right) - infer(model, left, right))
    if not model.inference_config.coarse_start:
        assert end_to_end.mean() <= 0.01 and end_to_end.max() <= 0.1, (end_to_end.mean(), end_to_end.max())
        return
    nets = {"torch": model, "onnx": OnnxNetwork(session)}
    for coarse in (False, True):  # the zero-start pass, then the coarse-started one: continuous in the weights
        config = InferenceConfig(scale=model.inference_config.scale, coarse_start=coarse)
        with engineering(True, int8=False):
            got, ref = (run(nets[k], left, right, config).disparity for k in ("onnx", "torch"))
        diff = np.abs(got - ref)
        assert diff.mean() <= 0.01 and diff.max() <= 0.1, (coarse, diff.mean(), diff.max())
    assert end_to_end.mean() <= 0.01 and (end_to_end > 0.1).mean() <= 5e-4, (end_to_end.mean(),
                                                                              (end_to_end > 0.1).sum())


def test_export_prints_no_exporter_chatter(export_run: tuple[Path, Path, subprocess.CompletedProcess]) -> None:
    """A fresh process (the exporter warns once per process): torchvision's missing detection ops, torch's
    deprecations, onnx_ir's pass log and the shared-axis notes are not the user's concern; the one line is."""
    _, onnx_file, done = export_run
    for chatter in ("torchvision", "FutureWarning", "onnx_ir", "axis name"):
        assert chatter not in done.stderr + done.stdout, (chatter, done.stderr[-2000:])
    assert f"wrote {onnx_file} (onnx" in done.stdout

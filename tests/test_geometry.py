"""Depth and point clouds: calibration readers (KITTI, Middlebury, YAML), exact planes, PNG/PLY writers, the CLI."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from optstereo.geometry import (
    Calibration,
    depth_to_points,
    disparity_to_depth,
    read_calibration,
    read_ply,
    write_depth_png,
    write_ply,
)
from pvm_labeler.common.errors import InputError
from pvm_labeler.common.io import read_grey_raw

RIG = Calibration(fx=700.0, fy=700.0, cx=320.0, cy=120.0, baseline=0.5)


def test_kitti_calibration_file(shared_data: Path) -> None:
    calib = read_calibration(shared_data / "kitti15/training/calib_cam_to_cam/000000.txt")
    assert calib.fx == pytest.approx(721.5377) and calib.cx == pytest.approx(609.5593)
    # (44.85728 + 339.5242) / 721.5377, the x-offset difference over f (SOURCES.md: 0.533 m)
    assert calib.baseline == pytest.approx((44.85728 + 339.5242) / 721.5377) and abs(calib.baseline - 0.533) < 1e-3
    assert calib.doffs == 0.0


def test_middlebury_calibration_file(shared_data: Path) -> None:
    calib = read_calibration(shared_data / "middlebury_eval3/trainingQ/Motorcycle/calib.txt")
    assert (calib.fx, calib.cx, calib.cy) == pytest.approx((999.421, 294.182, 252.932))
    assert calib.baseline == pytest.approx(0.193001) and calib.doffs == pytest.approx(32.778)


def test_yaml_calibration(tmp_path: Path) -> None:
    path = tmp_path / "rig.yaml"
    path.write_text("fx: 500\ncx: 100\ncy: 80\nbaseline: 0.12\n")
    assert read_calibration(path) == Calibration(500.0, 500.0, 100.0, 80.0, 0.12, 0.0)
    path.write_text("fx: 500\n")
    with pytest.raises(InputError, match="lacks"):
        read_calibration(path)
    other = tmp_path / "other.txt"
    other.write_text("hello=1\n")
    with pytest.raises(InputError, match="not a KITTI"):
        read_calibration(other)
    # hand-written mistakes are named with the file (each was a traceback or a bare ValueError)
    for text, named in (("fx: 700\ncx 320.0\ncy: 180\n", "not valid YAML (.*line 3)"),
                        ("fx=700 cx=320 cy=180 baseline=0.12\n", "a YAML calibration is 'key: value' lines"),
                        ("%YAML:1.0\n---\nK1: !!opencv-matrix\n", "an OpenCV FileStorage file"),
                        ("fx: seven hundred\ncx: 1\ncy: 1\nbaseline: 0.1\n", "fx must be a number, got 'seven"),
                        ("fx: 7\ncx: 1\ncy: 1\nbaseline: 0.1\nwidth: 640px\nheight: 2\n", "width must be a number")):
        path.write_text(text)
        with pytest.raises(InputError, match=f"{path.name}: {named}"):
            read_calibration(path)
    other.write_text("fx: 700\ncx: 320\ncy: 180\nbaseline: 0.12\n")
    with pytest.raises(InputError, match="read from a file named .yaml or .yml"):
        read_calibration(other)


def test_a_principal_point_far_from_the_centre_is_warned_about(caplog: pytest.LogCaptureFixture) -> None:
    """A 1280x720 calibration without its size on a 640x360 pair: the principal point at the corner is warned about
    (the depth would be off by 2x); a centred one is not."""
    with caplog.at_level("WARNING", logger="optstereo.geometry"):
        Calibration(1400.0, 1400.0, 639.5, 359.5, 0.12, 0.0, source="c.yaml").check_fits(360, 640)
    assert "principal point (639.5, 359.5) lies far from the centre of the 640x360 pair" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="optstereo.geometry"):
        Calibration(700.0, 700.0, 320.0, 180.0, 0.12, 0.0).check_fits(360, 640)
    assert not caplog.text


def test_fronto_parallel_plane_is_exact() -> None:
    z = 12.5
    disp = np.full((240, 640), RIG.fx * RIG.baseline / z, np.float32)
    depth = disparity_to_depth(disp, RIG)
    np.testing.assert_allclose(depth, z, rtol=1e-6)
    xyz, _ = depth_to_points(depth, RIG)
    np.testing.assert_allclose(xyz[:, 2], z, rtol=1e-6)
    # the principal point's ray is the optical axis; the pixel 100 columns right of it is 100 * z / fx to the right
    k = 120 * 640 + 420
    assert xyz[k, 0] == pytest.approx(100 * z / RIG.fx, rel=1e-5) and xyz[k, 1] == pytest.approx(0.0, abs=1e-6)


def test_slanted_plane_points_lie_on_the_plane() -> None:
    # plane Z = 5 + 0.01 * X: along a row, d(u) = fx B / Z with Z solving Z = 5 + 0.01 (u - cx) Z / fx
    u = np.arange(640, dtype=np.float64)
    z = 5.0 / (1.0 - 0.01 * (u - RIG.cx) / RIG.fx)
    disp = np.broadcast_to(RIG.fx * RIG.baseline / z, (240, 640)).astype(np.float64)
    calib = Calibration(700.0, 700.0, 320.0, 120.0, 0.5, doffs=2.0)
    depth = disparity_to_depth(disp - 2.0, calib)  # doffs is added back: the same depths
    np.testing.assert_allclose(depth[7], z, rtol=1e-5)
    xyz, _ = depth_to_points(depth, calib)
    np.testing.assert_allclose(xyz[:, 2], 5.0 + 0.01 * xyz[:, 0], rtol=1e-5)


def test_invalid_and_far_pixels_are_dropped(tmp_path: Path) -> None:
    disp = np.array([[35.0, np.nan, 0.0, -1.0, 3.5]], np.float32)
    depth = disparity_to_depth(disp, RIG, max_depth=50.0)
    assert depth[0, 0] == pytest.approx(10.0) and np.isnan(depth[0, 1:]).all()  # 3.5 px = 100 m > 50
    write_depth_png(tmp_path / "d.png", depth)
    raw = read_grey_raw(tmp_path / "d.png")
    assert raw.dtype == np.uint16 and raw[0, 0] == 10000 and (raw[0, 1:] == 0).all()


def test_ply_round_trip(tmp_path: Path) -> None:
    depth = np.array([[2.0, np.nan], [4.0, 8.0]], np.float32)
    image = np.arange(12, dtype=np.uint8).reshape(2, 2, 3)
    xyz, rgb = depth_to_points(depth, RIG, image)
    write_ply(tmp_path / "c.ply", xyz, rgb)
    back = read_ply(tmp_path / "c.ply")
    assert len(back) == 3
    np.testing.assert_allclose(back["z"], [2.0, 4.0, 8.0])
    assert back["red"].tolist() == [0, 6, 9]


def test_predict_cli_depth_and_ply(tmp_path: Path, shared_data: Path) -> None:
    import torch
    from conftest import TINY

    from optstereo.checkpoint import export_safetensors
    from optstereo.cli import predict_main
    from optstereo.models import build_model

    torch.manual_seed(0)
    ckpt = export_safetensors(tmp_path / "tiny.safetensors", build_model("optstereo", iters=2, **TINY))
    left = shared_data / "kitti15/training/image_2/000000_10.png"
    right = shared_data / "kitti15/training/image_3/000000_10.png"
    calib = shared_data / "kitti15/training/calib_cam_to_cam/000000.txt"
    args = ["--checkpoint", str(ckpt), str(left), str(right), "--out", str(tmp_path / "o"), "--device", "cpu"]
    result = CliRunner().invoke(predict_main, [*args, "--format", "depth-png", "--format", "ply", "--format", "npy",
                                               "--calib", str(calib), "--max-depth", "80"])
    assert result.exit_code == 0, result.output
    disp = np.load(tmp_path / "o/000000_10.npy")
    depth_mm = read_grey_raw(tmp_path / "o/000000_10_depth.png").astype(np.float64)
    rig = read_calibration(calib)
    expected = disparity_to_depth(disp, rig, 80.0)
    ok = np.isfinite(expected)
    fits = ok & (np.round(np.nan_to_num(expected) * 1000) <= 65535)  # beyond 65.535 m: 0 (it was clipped to it)
    assert (ok & ~fits).any()  # this frame has such depths (up to --max-depth 80)
    np.testing.assert_allclose(depth_mm[fits], np.round(expected[fits] * 1000), atol=1)
    assert (depth_mm[~fits] == 0).all()
    assert len(read_ply(tmp_path / "o/000000_10.ply")) == int(ok.sum())
    missing = CliRunner().invoke(predict_main, [*args, "--format", "ply"])
    assert missing.exit_code == 2 and "--calib" in missing.output


def test_depth_and_ply_of_a_rigs_folder(tmp_path: Path) -> None:
    """`--dataset folder --calib RIG --format depth-npy --format ply`: each pair gets its depth and point cloud, the
    same as predicting it alone (it was refused: one LEFT RIGHT pair only); a pair of another size than the
    calibration's stops the run before any pair is predicted."""
    import torch
    from conftest import TINY, make_folder

    from optstereo.checkpoint import export_safetensors
    from optstereo.cli import predict_main
    from optstereo.models import build_model

    torch.manual_seed(0)
    ckpt = export_safetensors(tmp_path / "tiny.safetensors", build_model("optstereo", iters=1, **TINY))
    rig = make_folder(tmp_path / "rig", n=2, size=(64, 128))
    calib = tmp_path / "rig.yaml"
    calib.write_text("fx: 100\ncx: 64\ncy: 32\nbaseline: 0.5\nwidth: 128\nheight: 64\n")
    common = ["--checkpoint", str(ckpt), "--calib", str(calib), "--format", "npy", "--format", "depth-npy",
              "--format", "ply", "--device", "cpu", "--quiet"]
    result = CliRunner().invoke(predict_main, [*common, "--dataset", "folder", "--root", str(rig), "--out",
                                               str(tmp_path / "all")])
    assert result.exit_code == 0 and "wrote 2 frames" in result.output, result.output
    one = CliRunner().invoke(predict_main, [*common, str(rig / "left/001.png"), str(rig / "right/001.png"), "--out",
                                            str(tmp_path / "one")])
    assert one.exit_code == 0, one.output
    for name in ("000", "001"):
        disp = np.load(tmp_path / "all" / f"{name}.npy")
        expected = disparity_to_depth(disp, read_calibration(calib))
        np.testing.assert_allclose(np.load(tmp_path / "all" / f"{name}_depth.npy"), expected, rtol=1e-6)
        assert len(read_ply(tmp_path / "all" / f"{name}.ply")) == int(np.isfinite(expected).sum())
    np.testing.assert_array_equal(np.load(tmp_path / "all/001_depth.npy"), np.load(tmp_path / "one/001_depth.npy"))
    calib.write_text("fx: 100\ncx: 64\ncy: 32\nbaseline: 0.5\nwidth: 256\nheight: 128\n")
    result = CliRunner().invoke(predict_main, [*common, "--dataset", "folder", "--root", str(rig), "--out",
                                               str(tmp_path / "other")])
    assert result.exit_code == 1 and "describes 256x128 images and the pair is 128x64" in result.output
    assert not list(tmp_path.glob("other/*"))  # nothing predicted


def test_a_datasets_own_calibrations_serve_its_pairs(tmp_path: Path, shared_data: Path) -> None:
    """`--dataset middlebury --format depth-npy`: Motorcycle's depth follows its own calib.txt (each Middlebury scene
    has its own focal length and baseline: one --calib for all gave wrong depths); pairs without one need --calib,
    named when it is missing (exit 2, nothing predicted)."""
    import torch
    from conftest import TINY

    from optstereo.checkpoint import export_safetensors
    from optstereo.cli import predict_main
    from optstereo.models import build_model

    torch.manual_seed(0)
    ckpt = export_safetensors(tmp_path / "tiny.safetensors", build_model("optstereo", iters=1, **TINY))
    args = ["--checkpoint", str(ckpt), "--dataset", "middlebury", "--root", str(shared_data), "--format", "npy",
            "--format", "depth-npy", "--device", "cpu", "--quiet", "--out"]
    refused = CliRunner().invoke(predict_main, [*args, str(tmp_path / "none")])
    assert refused.exit_code == 2, refused.output
    assert "2 pairs (middlebury2001-tsukuba, middlebury2003-cones) have none of their own" in refused.output
    assert not list(tmp_path.glob("none/*"))
    rig = tmp_path / "rig.yaml"
    rig.write_text("fx: 400\ncx: 200\ncy: 160\nbaseline: 0.1\n")
    done = CliRunner().invoke(predict_main, [*args, str(tmp_path / "o"), "--calib", str(rig)])
    assert done.exit_code == 0, done.output
    own = shared_data / "middlebury_eval3/trainingQ/Motorcycle/calib.txt"
    for name, calib in (("middlebury_eval3-trainingQ-Motorcycle", own), ("middlebury2001-tsukuba", rig)):
        disp = np.load(tmp_path / "o" / f"{name}.npy")
        np.testing.assert_allclose(np.load(tmp_path / "o" / f"{name}_depth.npy"),
                                   disparity_to_depth(disp, read_calibration(calib)), rtol=1e-6)


def test_a_point_cloud_of_the_confident_pixels(tmp_path: Path) -> None:
    """`--min-confidence 0.5 --format conf-npy --format ply --format depth-npy`: the depth and the cloud hold exactly
    the pixels whose confidence passes (they could not be combined: depth and PLY refused conf-* and the filter)."""
    import torch
    from conftest import TINY, make_folder

    from optstereo.checkpoint import export_safetensors
    from optstereo.cli import predict_main
    from optstereo.models import build_model

    torch.manual_seed(0)
    ckpt = export_safetensors(tmp_path / "tiny.safetensors", build_model("optstereo", iters=1, **TINY))
    rig = make_folder(tmp_path / "rig", n=1, size=(64, 128))
    calib = tmp_path / "rig.yaml"
    calib.write_text("fx: 100\ncx: 64\ncy: 32\nbaseline: 0.5\nwidth: 128\nheight: 64\n")
    result = CliRunner().invoke(predict_main, [
        "--checkpoint", str(ckpt), str(rig / "left/000.png"), str(rig / "right/000.png"), "--out", str(tmp_path / "o"),
        "--calib", str(calib), "--min-confidence", "0.5", "--format", "npy", "--format", "conf-npy", "--format",
        "depth-npy", "--format", "ply", "--device", "cpu", "--quiet"])
    assert result.exit_code == 0, result.output
    conf, disp = np.load(tmp_path / "o/000_conf.npy"), np.load(tmp_path / "o/000.npy")
    kept = conf >= 0.5
    assert 0 < kept.sum() < kept.size  # the filter acts on this pair
    assert np.isnan(disp[~kept]).all() and np.isfinite(disp[kept]).all()
    depth = np.load(tmp_path / "o/000_depth.npy")
    np.testing.assert_allclose(depth, disparity_to_depth(disp, read_calibration(calib)), rtol=1e-6)
    assert len(read_ply(tmp_path / "o/000.ply")) == int(np.isfinite(depth).sum()) <= int(kept.sum())


def test_kitti_submission_zip(tmp_path: Path, shared_data: Path, caplog: pytest.LogCaptureFixture) -> None:
    """--submission: only _10 frames, disp_0/<frame>_10.png, each 16-bit at its own image's size; checked."""
    import zipfile

    import cv2
    import torch
    from conftest import TINY

    from optstereo.checkpoint import export_safetensors
    from optstereo.cli import predict_main
    from optstereo.models import build_model
    from optstereo.submission import submission_problems

    src = shared_data / "kitti_unlabelled/kitti15_testing"
    root = tmp_path / "kitti" / "testing"
    for view in ("image_2", "image_3"):
        (root / view).mkdir(parents=True)
        for stem in ("000001_10", "000001_11"):
            (root / view / f"{stem}.png").symlink_to((src / view / f"{stem}.png").resolve())
        image = cv2.imread(str(src / view / "000002_10.png"))
        cv2.imwrite(str(root / view / "000002_10.png"), image[:370, :1224])  # KITTI's smaller frames exist too
    torch.manual_seed(0)
    ckpt = export_safetensors(tmp_path / "tiny.safetensors", build_model("optstereo", iters=1, **TINY))
    zip_path = tmp_path / "submit.zip"
    with caplog.at_level(logging.WARNING):
        result = CliRunner().invoke(predict_main, [
            "--checkpoint", str(ckpt), "--dataset", "kitti15", "--root", str(tmp_path / "kitti"), "--split",
            "testing", "--out", str(tmp_path / "pred"), "--format", "color", "--submission", str(zip_path),
            "--device", "cpu"])
    assert result.exit_code == 0, result.output
    # well formed, but 2 frames: the server's count is said (the line said "(checked)" only); the split is right
    assert "would refuse" in caplog.text and "it holds 2 frames; kitti15's testing split has 200" in caplog.text
    assert "split's frames" not in caplog.text
    assert submission_problems("kitti15", "training", 200) == [
        "it holds the 'training' split's frames; the server scores the testing split's (--split testing)"]
    assert submission_problems("kitti12", "testing", 195) == []
    assert sorted(p.name for p in (tmp_path / "pred/disp_0").iterdir()) == ["000001_10.png", "000002_10.png"]
    with zipfile.ZipFile(zip_path) as zf:  # the _11 pair was run and written beside them, then left out
        assert sorted(zf.namelist()) == ["disp_0/000001_10.png", "disp_0/000002_10.png"]
        sizes = [cv2.imdecode(np.frombuffer(zf.read(n), np.uint8), cv2.IMREAD_UNCHANGED).shape for n in
                 sorted(zf.namelist())]
    assert sizes == [(375, 1242), (370, 1224)]
    (tmp_path / "pred/disp_0/000002_10.png").unlink()
    from optstereo.inference.outputs import write_submission
    from pvm_labeler.common.datasets import discover

    with pytest.raises(ValueError, match="000002_10 missing"):
        write_submission(tmp_path / "pred", tmp_path / "again.zip", discover("kitti15", tmp_path / "kitti", "testing"))
    assert not (tmp_path / "again.zip").exists()


def test_a_calibration_of_another_image_size_is_refused(tmp_path: Path, shared_data: Path,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    """A half-size KITTI pair with the full-size calib_cam_to_cam.txt gave depths twice too large, silently: its
    S_rect_02 (1242 x 375) is checked before the network runs; a YAML's width / height and a principal point outside
    the image alike. --calib without a depth format is warned about (it was ignored silently)."""
    import cv2
    from conftest import TINY

    from optstereo.checkpoint import export_safetensors
    from optstereo.cli import predict_main
    from optstereo.models import build_model

    ckpt = export_safetensors(tmp_path / "tiny.safetensors", build_model("optstereo", iters=2, **TINY))
    calib = shared_data / "kitti15/training/calib_cam_to_cam/000000.txt"
    assert read_calibration(calib).size == (375, 1242)
    half = []
    for side in ("image_2", "image_3"):
        image = cv2.imread(str(shared_data / f"kitti15/training/{side}/000000_10.png"))
        half.append(tmp_path / f"{side}.png")
        cv2.imwrite(str(half[-1]), cv2.resize(image, (621, 188), interpolation=cv2.INTER_AREA))
    args = ["--checkpoint", str(ckpt), *map(str, half), "--out", str(tmp_path / "o"), "--format", "depth-npy"]
    result = CliRunner().invoke(predict_main, [*args, "--calib", str(calib)])
    assert result.exit_code == 1 and "describes 1242x375 images and the pair is 621x188" in result.output
    assert not (tmp_path / "o").exists()
    yaml_calib = tmp_path / "rig.yaml"
    yaml_calib.write_text("fx: 360\ncx: 900\ncy: 90\nbaseline: 0.54\n")
    result = CliRunner().invoke(predict_main, [*args, "--calib", str(yaml_calib)])
    assert result.exit_code == 1 and "principal point (900, 90) lies outside the 621x188 pair" in result.output
    yaml_calib.write_text("fx: 360\ncx: 310\ncy: 94\nbaseline: 0.54\nwidth: 621\nheight: 188\n")
    assert CliRunner().invoke(predict_main, [*args, "--calib", str(yaml_calib)]).exit_code == 0
    with caplog.at_level(logging.WARNING):
        done = CliRunner().invoke(predict_main, [*args[:-2], "--format", "npy", "--calib", str(yaml_calib)])
    assert done.exit_code == 0 and "--calib read by the depth and point-cloud formats only" in caplog.text


def test_max_depth_must_be_positive(tmp_path: Path) -> None:
    """--max-depth 0 (read as "off") or below wrote an empty PLY and an all-zero depth PNG with exit 0."""
    from optstereo.cli import predict_main

    for value in ("0", "-1"):
        result = CliRunner().invoke(predict_main, ["--checkpoint", "pretrained", "l.png", "r.png", "--out",
                                                   str(tmp_path / "o"), "--max-depth", value])
        assert result.exit_code == 2, result.output
        assert "'--max-depth'" in result.output and "range x>0" in result.output

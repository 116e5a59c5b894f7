"""Dataset readers on the real copies in ../shared/data, on tiny fakes of each layout, and on bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from pvm_labeler.common import io
from pvm_labeler.common.datasets import DATASETS, check_pair_sizes, discover, load_pair, make_layered_scene
from pvm_labeler.common.errors import InputError


def _finite_frac(a: np.ndarray) -> float:
    return float(np.isfinite(a).mean())


class TestKitti15:
    def test_discover(self, shared_data: Path) -> None:
        refs = discover("kitti15", shared_data / "kitti15")
        assert len(refs) == 15
        ids = [r.frame_id for r in refs]
        assert ids == sorted(ids) and ids[0] == "000000_10" and ids[-1] == "000046_10"
        by_id = {r.frame_id: r for r in refs}
        assert by_id["000000_10"].gt.parent.name == "disp_occ_0" and by_id["000000_10"].gt_noc is not None
        assert by_id["000001_10"].gt.parent.name == "disp_noc_0"  # only noc: gt falls back to it
        assert by_id["000046_10"].gt.parent.name == "disp_occ_0" and by_id["000046_10"].gt_noc is None

    def test_load(self, shared_data: Path) -> None:
        ref = {r.frame_id: r for r in discover("kitti15", shared_data / "kitti15")}["000000_10"]
        s = load_pair(ref)
        assert s.left.shape == s.right.shape == (375, 1242, 3) and s.left.dtype == np.uint8
        assert s.gt.dtype == np.float32 and s.gt_right is None
        # occ covers noc: every noc pixel is in occ with the same value (the official files differ by one
        # quantisation step, 1/256 px, on 29 of 87,712 pixels of this frame).
        noc = np.isfinite(s.gt_noc)
        assert noc.sum() < np.isfinite(s.gt).sum()
        np.testing.assert_allclose(s.gt[noc], s.gt_noc[noc], rtol=0, atol=1 / 256 + 1e-6)
        assert abs(float(np.nanmax(s.gt)) - 64.1) < 0.05

    def test_testing_split_missing(self, shared_data: Path) -> None:
        with pytest.raises(InputError, match="split folder 'testing' not found"):
            discover("kitti15", shared_data / "kitti15", split="testing")


class TestKitti12:
    def test_load(self, shared_data: Path) -> None:
        (ref,) = discover("kitti12", shared_data / "kitti12")
        s = load_pair(ref)
        assert s.left.shape == (376, 1241, 3)
        assert abs(_finite_frac(s.gt) - 0.294) < 0.005 and abs(_finite_frac(s.gt_noc) - 0.288) < 0.005
        assert abs(float(np.nanmax(s.gt)) - 147.0) < 0.05


class TestMiddlebury:
    def test_all_layouts(self, shared_data: Path) -> None:
        refs = {r.frame_id: r for r in discover("middlebury", shared_data)}
        assert set(refs) == {"middlebury2001-tsukuba", "middlebury2003-cones", "middlebury_eval3-trainingQ-Motorcycle"}
        tsukuba = load_pair(refs["middlebury2001-tsukuba"])
        assert tsukuba.left.shape == (288, 384, 3)
        assert np.nanmin(tsukuba.gt) == 5 and np.nanmax(tsukuba.gt) == 14  # value / 16
        assert abs(_finite_frac(tsukuba.gt) - (1 - 0.207)) < 0.005
        cones = load_pair(refs["middlebury2003-cones"])
        assert np.nanmin(cones.gt) == 5.5 and np.nanmax(cones.gt) == 55.0  # value / 4
        moto = load_pair(refs["middlebury_eval3-trainingQ-Motorcycle"])
        assert moto.max_disp == 70 and np.isnan(moto.gt).sum() == 7684
        mask = cv2.imread(str(shared_data / "middlebury_eval3/trainingQ/Motorcycle/mask0nocc.png"), 0)
        np.testing.assert_array_equal(np.isfinite(moto.gt_noc), (mask == 255) & np.isfinite(moto.gt))

    def test_root_is_scene(self, shared_data: Path) -> None:
        (ref,) = discover("middlebury", shared_data / "middlebury2003/cones")
        assert ref.frame_id == "cones"


class TestSceneFlow:
    def test_load(self, shared_data: Path) -> None:
        (ref,) = discover("sceneflow", shared_data / "sceneflow")
        assert ref.frame_id == "flyingthings3d-A-0032-0006"
        s = load_pair(ref)
        assert s.left.shape == (540, 960, 3)  # RGBA -> RGB
        assert _finite_frac(s.gt) == 1.0
        assert abs(_finite_frac(s.gt_noc) - 0.85) < 0.01  # 15 % occluded

    def test_official_layout(self, tmp_path: Path, shared_data: Path) -> None:
        src = shared_data / "sceneflow/flyingthings3d"
        for split in ("TRAIN", "TEST"):
            for view in ("left", "right"):
                dst = tmp_path / f"frames_cleanpass/{split}/A/0000/{view}"
                dst.mkdir(parents=True)
                shutil.copy(src / f"RGB_cleanpass/{view}/A-0032-0006.png", dst / "0006.png")
                ddir = tmp_path / f"disparity/{split}/A/0000/{view}"
                ddir.mkdir(parents=True)
                shutil.copy(src / "disparity/left/A-0032-0006.pfm", ddir / "0006.pfm")
        (train,) = discover("sceneflow", tmp_path)
        (test,) = discover("sceneflow", tmp_path, split="testing")
        assert train.frame_id == "TRAIN-A-0000-0006" and test.frame_id == "TEST-A-0000-0006"
        s = load_pair(train)
        assert s.gt_right is not None and s.gt_noc is None


class TestFolder:
    def _make(self, root: Path, n: int = 3, size: tuple[int, int] = (20, 30)) -> None:
        for view in ("left", "right", "gt"):
            (root / view).mkdir(parents=True)
        for i in range(n):
            img = np.full((*size, 3), 40 * i, np.uint8)
            io.write_image(root / "left" / f"{i:04d}.png", img)
            io.write_image(root / "right" / f"{i:04d}.png", img)
            io.write_kitti_disp(root / "gt" / f"{i:04d}.png", np.full(size, 2.5 + i, np.float32))

    def test_load(self, tmp_path: Path) -> None:
        self._make(tmp_path)
        refs = discover("folder", tmp_path)
        assert [r.frame_id for r in refs] == ["0000", "0001", "0002"]
        s = load_pair(refs[2])
        assert s.gt is not None and (s.gt == 4.5).all()

    def test_globs(self, tmp_path: Path) -> None:
        self._make(tmp_path)
        left, right = str(tmp_path / "left/000[01].png"), str(tmp_path / "right/*[01].png")
        refs = discover("folder", None, left=left, right=right)
        assert [r.frame_id for r in refs] == ["0000", "0001"] and all(r.gt is None for r in refs)
        with pytest.raises(InputError, match=r"count mismatch: 2 images in .*000\[01\].png vs 3 in"):
            discover("folder", None, left=str(tmp_path / "left/000[01].png"), right=str(tmp_path / "right/*.png"))

    def test_count_mismatch(self, tmp_path: Path) -> None:
        self._make(tmp_path)
        (tmp_path / "right/0002.png").unlink()
        with pytest.raises(InputError, match=r"count mismatch: 3 images in .*left vs 2 in .*right"):
            discover("folder", tmp_path)

    def test_size_mismatch(self, tmp_path: Path) -> None:
        self._make(tmp_path)
        io.write_image(tmp_path / "right/0001.png", np.zeros((20, 31, 3), np.uint8))
        ref = discover("folder", tmp_path)[1]
        with pytest.raises(InputError, match=r"sizes differ: \(20, 30\) vs \(20, 31\).*0001.png"):
            check_pair_sizes(ref)
        with pytest.raises(InputError, match=r"sizes differ.*right/0001.png"):
            load_pair(ref)


class TestSample:
    def test_sample(self) -> None:
        refs = discover("sample", None)
        assert [r.frame_id for r in refs] == ["motorcycle", "synthetic-000", "synthetic-001", "synthetic-002"]
        moto = load_pair(refs[0])
        assert moto.left.shape == (500, 741, 3) and moto.max_disp == 64
        assert np.isnan(moto.gt).sum() == 27226
        assert float(np.nanmax(moto.gt)) < 64

    def test_synthetic_gt_is_exact(self) -> None:
        scene = make_layered_scene(96, 128, 5)
        left, right = scene["left"].astype(np.float64), scene["right"].astype(np.float64)
        gt = scene["gt_noc"]
        # Integer-disparity layers are exact copies: left(x) == right(x - d) wherever the GT is an integer.
        ys, xs = np.nonzero(np.isfinite(gt) & (gt == np.round(gt)) & (gt >= 30))
        assert len(ys) > 100
        np.testing.assert_array_equal(left[ys, xs], right[ys, xs - gt[ys, xs].astype(int)])
        # Occlusion: noc is a strict subset and the right GT is positive too.
        assert np.isfinite(scene["gt_noc"]).sum() < np.isfinite(scene["gt"]).sum()
        assert np.nanmin(scene["gt_right"]) > 0

    def test_deterministic(self) -> None:
        a, b = make_layered_scene(64, 96, 1), make_layered_scene(64, 96, 1)
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])


class TestErrors:
    def test_unknown_dataset(self) -> None:
        with pytest.raises(InputError, match="unknown dataset 'kitti2099'.*kitti15"):
            discover("kitti2099", None)

    def test_missing_root(self, tmp_path: Path) -> None:
        with pytest.raises(InputError, match="kitti15 root not found.*nowhere"):
            discover("kitti15", tmp_path / "nowhere")

    def test_empty_root(self, tmp_path: Path) -> None:
        with pytest.raises(InputError, match="no stereo pairs found for dataset 'middlebury'"):
            discover("middlebury", tmp_path)

    def test_kitti_missing_right(self, tmp_path: Path, shared_data: Path) -> None:
        for sub in ("image_2", "image_3"):
            (tmp_path / "training" / sub).mkdir(parents=True)
        for i in ("000000_10", "000001_10"):
            shutil.copy(shared_data / f"kitti15/training/image_2/{i}.png", tmp_path / f"training/image_2/{i}.png")
        shutil.copy(shared_data / "kitti15/training/image_3/000000_10.png", tmp_path / "training/image_3")
        with pytest.raises(InputError, match=r"count mismatch.*no right image for .*image_2/000001_10.png"):
            discover("kitti15", tmp_path)

    def test_corrupt_png_names_file(self, tmp_path: Path, shared_data: Path) -> None:
        for sub in ("image_2", "image_3"):
            (tmp_path / "training" / sub).mkdir(parents=True)
            shutil.copy(shared_data / f"kitti15/training/{sub}/000000_10.png", tmp_path / "training" / sub)
        path = tmp_path / "training/image_3/000000_10.png"
        path.write_bytes(path.read_bytes()[:20000])
        (ref,) = discover("kitti15", tmp_path)
        with pytest.raises(InputError, match="corrupt or truncated image.*image_3/000000_10.png"):
            load_pair(ref)

    def test_names(self) -> None:
        assert DATASETS == ("kitti15", "kitti12", "middlebury", "sceneflow", "folder", "kitti_unlabelled", "sample")

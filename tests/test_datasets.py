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


def _cones(shared_data: Path, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The top ``rows`` x ``cols`` at column 260 of ../shared's Cones (some GT 0 = unknown lies there): left, right
    (RGB uint8) and its raw 8-bit GT map."""
    src = shared_data / "middlebury2003/cones"
    crop = (slice(0, rows), slice(260, 260 + cols))
    return (io.read_image(src / "im2.png")[crop], io.read_image(src / "im6.png")[crop],
            io.read_grey_raw(src / "disp2.png")[crop])


def _middlebury_2005_scene(folder: Path, shared_data: Path, rows: int, gt_folder: Path | None = None) -> np.ndarray:
    """A 2005 / 2006 scene (view1, view5, disp1, disp5) from Cones' pixels; returns the raw map written as disp1."""
    left, right, raw = _cones(shared_data, rows, 64)
    folder.mkdir(parents=True)
    io.write_image(folder / "view1.png", left)
    io.write_image(folder / "view5.png", right)
    gt_folder = gt_folder or folder
    io.write_image(gt_folder / "disp1.png", raw)
    io.write_image(gt_folder / "disp5.png", raw[:, ::-1].copy())
    return raw


class TestMiddlebury2005:
    """The 2005 / 2006 layout: view1 / view5, disp1 / disp5 with value / 1, 2, 3 by size, 0 = unknown."""

    def test_feature(self, tmp_path: Path, shared_data: Path) -> None:
        raws = {name: _middlebury_2005_scene(tmp_path / name, shared_data, rows)
                for name, rows in [("FullSize/Art", 40), ("HalfSize/Books", 40), ("ThirdSize/Dolls", 40),
                                   ("scenes2006/Aloe", 370)]}  # the last: no size folder, 370 rows = ThirdSize
        refs = {r.frame_id: r for r in discover("middlebury", tmp_path)}
        assert set(refs) == {"FullSize-Art", "HalfSize-Books", "ThirdSize-Dolls", "scenes2006-Aloe"}
        for (name, raw), factor in zip(raws.items(), (1, 2, 3, 3), strict=True):
            assert (raw == 0).any() and (raw > 0).any()
            s = load_pair(refs[name.replace("/", "-")])
            want = np.where(raw == 0, np.nan, raw.astype(np.float32) / factor).astype(np.float32)
            np.testing.assert_array_equal(s.gt, want)
            np.testing.assert_array_equal(s.gt_right, want[:, ::-1])
            assert s.gt_noc is None and s.max_disp is None and s.left.shape == (raw.shape[0], 64, 3)
        assert refs["HalfSize-Books"].meta["gt_scale"] == 2.0

    def test_illumination_folders(self, tmp_path: Path, shared_data: Path) -> None:
        """The full archives: <scene>/Illum<i>/Exp<e>/view1.png, GT in <scene>/."""
        scene = tmp_path / "ThirdSize/Laundry"
        raw = _middlebury_2005_scene(scene / "Illum1/Exp0", shared_data, 40, gt_folder=scene)
        (ref,) = discover("middlebury", tmp_path)
        assert ref.frame_id == "ThirdSize-Laundry-Illum1-Exp0" and ref.gt == scene / "disp1.png"
        np.testing.assert_array_equal(load_pair(ref).gt, np.where(raw == 0, np.nan, raw / np.float32(3)))

    def test_no_gt(self, tmp_path: Path, shared_data: Path) -> None:
        _middlebury_2005_scene(tmp_path / "Art", shared_data, 40)
        for name in ("disp1.png", "disp5.png"):
            (tmp_path / "Art" / name).unlink()
        (ref,) = discover("middlebury", tmp_path)  # no GT: the size is never needed
        assert ref.gt is None and load_pair(ref).gt is None

    def test_exception(self, tmp_path: Path, shared_data: Path) -> None:
        _middlebury_2005_scene(tmp_path / "a/Art", shared_data, 40)
        with pytest.raises(InputError, match=r"cannot tell the size of .*a/Art/view1.png.*40 rows.*1110 / 555 / 370"):
            discover("middlebury", tmp_path / "a")
        _middlebury_2005_scene(tmp_path / "b/HalfSize/Art", shared_data, 370)
        with pytest.raises(InputError, match=r"HalfSize folder \(555 rows\) but has 370 rows.*ThirdSize"):
            discover("middlebury", tmp_path / "b")


def _eth3d_scene(folder: Path, gt_folder: Path | None, shared_data: Path) -> tuple[np.ndarray, np.ndarray]:
    """An ETH3D scene (grey im0 / im1, calib.txt; disp0GT.pfm, mask0nocc.png in ``gt_folder``) from the top-left
    48 x 96 of ../shared's MiddEval3 Motorcycle (inf, mask 0, 128 and 255 all occur there); returns (GT, mask)."""
    src = shared_data / "middlebury_eval3/trainingQ/Motorcycle"
    crop = (slice(0, 48), slice(0, 96))
    folder.mkdir(parents=True)
    for name in ("im0.png", "im1.png"):
        io.write_image(folder / name, io.read_image(src / name)[crop][:, :, 0].copy())  # ETH3D images are grey
    shutil.copy(src / "calib.txt", folder / "calib.txt")  # ndisp=70
    gt, mask = io.read_pfm(src / "disp0GT.pfm")[crop], io.read_grey_raw(src / "mask0nocc.png")[crop]
    if gt_folder is not None:
        gt_folder.mkdir(parents=True, exist_ok=True)
        io.write_pfm(gt_folder / "disp0GT.pfm", gt)
        io.write_image(gt_folder / "mask0nocc.png", mask)
    return gt, mask


class TestEth3d:
    """ETH3D two-view: two_view_training/<scene>/im0, im1, calib.txt; two_view_training_gt/<scene>/disp0GT.pfm
    (inf = unknown), mask0nocc.png (255 = non-occluded)."""

    def test_feature(self, tmp_path: Path, shared_data: Path) -> None:
        train, gt_root = tmp_path / "two_view_training", tmp_path / "two_view_training_gt"
        gt, mask = _eth3d_scene(train / "delivery_area_1l", gt_root / "delivery_area_1l", shared_data)
        _eth3d_scene(train / "electro_1s", train / "electro_1s", shared_data)  # both archives unpacked in one folder
        _eth3d_scene(tmp_path / "two_view_test/lakeside_1l", None, shared_data)
        refs = discover("eth3d", tmp_path)
        assert [r.frame_id for r in refs] == ["delivery_area_1l", "electro_1s"]
        assert refs[1].gt == train / "electro_1s/disp0GT.pfm"
        s = load_pair(refs[0])
        assert s.left.shape == (48, 96, 3) and (s.left[..., 0] == s.left[..., 2]).all()  # grey -> 3 channels
        assert np.isinf(gt).sum() > 0 and {0, 128, 255} <= set(np.unique(mask))
        np.testing.assert_array_equal(s.gt, np.where(np.isinf(gt), np.nan, gt))
        np.testing.assert_array_equal(s.gt_noc, np.where((mask == 255) & np.isfinite(gt), gt, np.nan))
        assert s.gt_right is None and s.max_disp == 70  # calib.txt ndisp
        (test,) = discover("eth3d", tmp_path, split="testing")
        assert test.frame_id == "lakeside_1l" and test.gt is None and load_pair(test).gt is None

    def test_root_is_a_scene(self, tmp_path: Path, shared_data: Path) -> None:
        _eth3d_scene(tmp_path / "playground_1l", tmp_path / "playground_1l", shared_data)
        (ref,) = discover("eth3d", tmp_path / "playground_1l")
        assert ref.frame_id == "playground_1l" and ref.gt is not None and "noc_mask" in ref.meta

    def test_exception(self, tmp_path: Path, shared_data: Path) -> None:
        _eth3d_scene(tmp_path / "two_view_training/terrace_1s", None, shared_data)
        with pytest.raises(InputError, match="eth3d split folder for 'testing' not found.*two_view_test"):
            discover("eth3d", tmp_path, split="testing")
        (tmp_path / "two_view_training/terrace_1s/im1.png").unlink()
        with pytest.raises(InputError, match=r"left image .*terrace_1s/im0.png has no right image"):
            discover("eth3d", tmp_path)


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

    def test_webp(self, tmp_path: Path) -> None:
        # lossless WebP (quality > 100): the pair decodes to the pixels written, RGB order kept
        rng = np.random.default_rng(0)
        rgb = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
        for view in ("left", "right"):
            (tmp_path / view).mkdir()
            assert cv2.imwrite(str(tmp_path / view / "a.webp"), rgb[..., ::-1], [cv2.IMWRITE_WEBP_QUALITY, 101])
        refs = discover("folder", tmp_path)
        assert [r.frame_id for r in refs] == ["a"]
        np.testing.assert_array_equal(load_pair(refs[0]).left, rgb)

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
        assert DATASETS == ("kitti15", "kitti12", "middlebury", "eth3d", "sceneflow", "folder", "kitti_unlabelled",
                            "sample")


def test_folder_ids_keep_any_script_and_hidden_files_are_no_pairs(tmp_path: Path) -> None:
    """日本.png and 東京.png both became the id "frame" (a duplicate that stopped the run); .x.png and macOS's ._x.png
    resource forks were read as pairs (a corrupt header that stopped the run)."""
    image = np.zeros((8, 16, 3), np.uint8)
    for side in ("left", "right"):
        for name in ("日本.png", "東京.png", "ünï café#1.png", "plain.png"):
            io.write_image(tmp_path / side / name, image)
        (tmp_path / side / "._plain.png").write_bytes(b"\x00\x05\x16\x07 AppleDouble")
        (tmp_path / side / ".hidden.png").write_bytes(b"not an image")
    ids = [ref.frame_id for ref in discover("folder", tmp_path)]
    assert ids == sorted(["日本", "東京", "ünï-café-1", "plain"])
    assert [load_pair(ref).left.shape for ref in discover("folder", tmp_path)] == [(8, 16, 3)] * 4

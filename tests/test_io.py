"""Image and disparity I/O: round trips, conversions of grey/16-bit/RGBA images, clear errors on bad files."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from pvm_labeler.common import io
from pvm_labeler.common.errors import InputError


class TestPFM:
    def test_roundtrip(self, tmp_path: Path, rng: np.random.Generator) -> None:
        disp = rng.uniform(0, 100, size=(7, 11)).astype(np.float32)
        disp[0, 0] = np.inf
        io.write_pfm(tmp_path / "d.pfm", disp)
        again = io.read_pfm(tmp_path / "d.pfm")
        np.testing.assert_array_equal(again, disp)

    def test_rows_bottom_to_top_and_endianness(self, tmp_path: Path) -> None:
        # Hand-made big-endian file (positive scale): stored rows are bottom first.
        rows = np.array([[1, 2], [3, 4]], dtype=">f4")  # stored order: row "bottom" = [1, 2]
        (tmp_path / "b.pfm").write_bytes(b"Pf\n2 2\n1.0\n" + rows.tobytes())
        np.testing.assert_array_equal(io.read_pfm(tmp_path / "b.pfm"), [[3, 4], [1, 2]])

    def test_colour_pfm(self, tmp_path: Path) -> None:
        data = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
        io.write_pfm(tmp_path / "c.pfm", data)
        np.testing.assert_array_equal(io.read_pfm(tmp_path / "c.pfm"), data)

    def test_exception(self, tmp_path: Path) -> None:
        (tmp_path / "bad.pfm").write_bytes(b"P6\n2 2\n255\n")
        with pytest.raises(InputError, match="bad.pfm"):
            io.read_pfm(tmp_path / "bad.pfm")
        (tmp_path / "short.pfm").write_bytes(b"Pf\n4 4\n-1.0\n" + b"\0" * 12)
        with pytest.raises(InputError, match="truncated PFM.*expected 64"):
            io.read_pfm(tmp_path / "short.pfm")

    def test_real_middlebury(self, shared_data: Path) -> None:
        disp = io.read_pfm(shared_data / "middlebury_eval3/trainingQ/Motorcycle/disp0GT.pfm")
        assert disp.shape == (497, 741)
        finite = disp[np.isfinite(disp)]
        assert np.isinf(disp).sum() == 7684  # SOURCES.md: 7,684 px without GT
        assert 9.1 < finite.min() < 9.2 and 62.8 < finite.max() < 62.9


class TestKittiDisp:
    def test_roundtrip(self, tmp_path: Path) -> None:
        disp = np.array([[0.0, 1.5, np.nan], [100.25, 255.99609375, 0.001]], dtype=np.float32)
        io.write_kitti_disp(tmp_path / "k.png", disp)
        raw = cv2.imread(str(tmp_path / "k.png"), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16
        np.testing.assert_array_equal(raw, [[0, 384, 0], [25664, 65535, 1]])
        again = io.read_kitti_disp(tmp_path / "k.png")
        np.testing.assert_array_equal(np.isnan(again), [[True, False, True], [False, False, False]])
        assert again[0, 1] == 1.5 and again[1, 0] == 100.25

    def test_real_kitti(self, shared_data: Path) -> None:
        disp = io.read_kitti_disp(shared_data / "kitti15/training/disp_noc_0/000006_10.png")
        assert disp.shape == (375, 1242)
        assert abs(np.nanmax(disp) - 115.9) < 0.1  # SOURCES.md: frame 000006 max 115.9 px
        assert 0.12 < np.isfinite(disp).mean() < 0.25

    def test_exception(self, tmp_path: Path) -> None:
        cv2.imwrite(str(tmp_path / "eight.png"), np.zeros((4, 4), np.uint8))
        with pytest.raises(InputError, match="eight.png.*16-bit"):
            io.read_kitti_disp(tmp_path / "eight.png")


class TestDisparityFile:
    def test_each_suffix_round_trips(self, tmp_path: Path) -> None:
        disp = np.array([[1.5, np.nan], [40.25, 0.0]], np.float32)
        io.write_disparity_file(tmp_path / "d.png", disp)
        io.write_disparity_file(tmp_path / "d.pfm", disp)
        io.write_disparity_file(tmp_path / "d.npy", disp.astype(np.float64))
        kitti = io.read_kitti_disp(tmp_path / "d.png")  # x 256 exactly here; 0 and NaN are "no disparity"
        np.testing.assert_array_equal(kitti, np.array([[1.5, np.nan], [40.25, np.nan]], np.float32))
        pfm = io.read_pfm(tmp_path / "d.pfm")  # Middlebury's convention: a pixel without a value is inf
        np.testing.assert_array_equal(pfm, np.array([[1.5, np.inf], [40.25, 0.0]], np.float32))
        npy = np.load(tmp_path / "d.npy")
        assert npy.dtype == np.float32
        np.testing.assert_array_equal(npy, disp)

    def test_exception(self, tmp_path: Path) -> None:
        with pytest.raises(InputError, match=r"d.tif: a disparity file is one of png, pfm, npy"):
            io.write_disparity_file(tmp_path / "d.tif", np.zeros((2, 2), np.float32))
        assert not (tmp_path / "d.tif").exists()


class TestReadImage:
    def test_rgb_order(self, tmp_path: Path) -> None:
        bgr = np.zeros((2, 3, 3), np.uint8)
        bgr[..., 0] = 10  # blue in OpenCV's order
        cv2.imwrite(str(tmp_path / "c.png"), bgr)
        img = io.read_image(tmp_path / "c.png")
        assert img.shape == (2, 3, 3) and img.dtype == np.uint8
        assert (img[..., 2] == 10).all() and (img[..., 0] == 0).all()

    def test_grey_replicated(self, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
        grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
        cv2.imwrite(str(tmp_path / "g.png"), grey)
        with caplog.at_level(logging.INFO, logger="pvm_labeler.common.io"):
            img = io.read_image(tmp_path / "g.png")
        assert img.shape == (3, 4, 3)
        for c in range(3):
            np.testing.assert_array_equal(img[..., c], grey)
        assert "g.png: grey image replicated" in caplog.text

    def test_16bit_scaled(self, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
        wide = np.array([[0, 257, 65535, 128 * 257]], dtype=np.uint16)
        cv2.imwrite(str(tmp_path / "w.png"), np.dstack([wide] * 3))
        with caplog.at_level(logging.INFO, logger="pvm_labeler.common.io"):
            img = io.read_image(tmp_path / "w.png")
        assert img.dtype == np.uint8
        np.testing.assert_array_equal(img[0, :, 0], [0, 1, 255, 128])
        assert "16-bit image scaled" in caplog.text and "12-bit" not in caplog.text

    def test_16bit_image_of_12_bit_data_is_warned_about(self, tmp_path: Path,
                                                        caplog: pytest.LogCaptureFixture) -> None:
        """12-bit sensor data in a 16-bit PNG (values x 16 at most 4095) became an image of at most 16 grey levels,
        and label density fell from 75 to 45 %, with an INFO line only."""
        data = np.array([[0, 1000, 4095]], dtype=np.uint16)
        cv2.imwrite(str(tmp_path / "d.png"), np.dstack([data] * 3))
        with caplog.at_level(logging.WARNING, logger="pvm_labeler.common.io"):
            io.read_image(tmp_path / "d.png")
        assert "d.png: a 16-bit image whose values stop at 4095 (10- or 12-bit data?)" in caplog.text

    def test_rgba_alpha_dropped(self, shared_data: Path, caplog: pytest.LogCaptureFixture) -> None:
        path = shared_data / "sceneflow/flyingthings3d/RGB_cleanpass/left/A-0032-0006.png"
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert raw.shape[2] == 4
        with caplog.at_level(logging.INFO, logger="pvm_labeler.common.io"):
            img = io.read_image(path)
        assert img.shape == (540, 960, 3)
        np.testing.assert_array_equal(img, raw[..., 2::-1])
        assert "alpha channel dropped" in caplog.text

    @pytest.mark.parametrize("nbytes", [0, 30, 30000])
    def test_truncated(self, tmp_path: Path, shared_data: Path, nbytes: int) -> None:
        data = (shared_data / "kitti15/training/image_2/000000_10.png").read_bytes()[:nbytes]
        (tmp_path / "t.png").write_bytes(data)
        with pytest.raises(InputError, match=r"t\.png"):
            io.read_image(tmp_path / "t.png")

    def test_missing(self, tmp_path: Path) -> None:
        with pytest.raises(InputError, match="file not found.*nope.png"):
            io.read_image(tmp_path / "nope.png")

    def test_image_size_header_only(self, shared_data: Path, tmp_path: Path) -> None:
        assert io.image_size(shared_data / "kitti12/training/colored_0/000070_10.png") == (376, 1241)
        assert io.image_size(shared_data / "middlebury_eval3/trainingQ/Motorcycle/disp0GT.pfm") == (497, 741)
        (tmp_path / "junk.png").write_bytes(b"not a png at all")
        with pytest.raises(InputError, match="junk.png"):
            io.image_size(tmp_path / "junk.png")

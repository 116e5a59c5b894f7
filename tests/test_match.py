"""`pvm-label match` (issue 52): its output is pvm_labeler.dense's, bit for bit, in each format and both forms; bad
input fails naming the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner, Result
from conftest import make_folder

import pvm_labeler.job.progress as progress
from pvm_labeler.cli import main
from pvm_labeler.common import io
from pvm_labeler.common.datasets import discover, load_pair, make_layered_scene
from pvm_labeler.config import LabelerConfig
from pvm_labeler.dense import fill_rows_nearest, sgm_left
from pvm_labeler.match import match_dataset

MAX_DISP = 48  # the layered scene's GT reaches 44 px


def _invoke(*args: object) -> Result:
    return CliRunner().invoke(main, ["match", *(str(a) for a in args)])


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, np.ndarray]:
    """A 48x128 layered scene as two PNG files and dense.sgm_left's disparity of it (NaN = none)."""
    root = tmp_path_factory.mktemp("scene")
    s = make_layered_scene(48, 128, 0)
    io.write_image(root / "left.png", s["left"])
    io.write_image(root / "right.png", s["right"])
    disp, _ = sgm_left(s["left"], s["right"], LabelerConfig(), MAX_DISP)
    assert np.isnan(disp).any() and not np.isnan(disp).all(axis=1).any()  # holes, and every row has a value
    return root / "left.png", root / "right.png", disp


def _kitti_png(disp: np.ndarray) -> np.ndarray:
    """What a KITTI PNG holds after the round trip: round(d x 256) / 256, NaN where d is none or <= 0."""
    ok = np.isfinite(disp) & (disp > 0)
    return np.where(ok, np.clip(np.round(np.where(ok, disp, 0) * 256), 1, 65535) / 256, np.nan).astype(np.float32)


class TestPair:
    def test_feature(self, scene, tmp_path: Path) -> None:
        """Every format holds dense.fill_rows_nearest(dense.sgm_left(...)) exactly (PNG: to its 1/256 step)."""
        left, right, disp = scene
        result = _invoke(left, right, "--out", tmp_path, "--max-disp", MAX_DISP, "--format", "png", "--format", "pfm",
                         "--format", "npy")
        assert result.exit_code == 0, result.output
        want = fill_rows_nearest(disp)
        assert np.isfinite(want).all()
        np.testing.assert_array_equal(np.load(tmp_path / "left.npy"), want)
        np.testing.assert_array_equal(io.read_pfm(tmp_path / "left.pfm"), want)
        np.testing.assert_array_equal(io.read_kitti_disp(tmp_path / "left.png"), _kitti_png(want))
        assert str(tmp_path / "left.png") in result.output

    def test_no_fill(self, scene, tmp_path: Path) -> None:
        left, right, disp = scene
        result = _invoke(left, right, "--out", tmp_path, "--max-disp", MAX_DISP, "--no-fill", "--format", "npy",
                         "--format", "png")
        assert result.exit_code == 0, result.output
        np.testing.assert_array_equal(np.load(tmp_path / "left.npy"), disp)  # the holes stay NaN
        raw = io.read_grey_raw(tmp_path / "left.png")
        assert (raw[np.isnan(disp)] == 0).all()
        np.testing.assert_array_equal(io.read_kitti_disp(tmp_path / "left.png"), _kitti_png(disp))

    def test_default_format_is_kitti_png(self, scene, tmp_path: Path) -> None:
        left, right, _ = scene
        assert _invoke(left, right, "--out", tmp_path, "--max-disp", MAX_DISP).exit_code == 0
        assert sorted(p.name for p in tmp_path.iterdir()) == ["left.png"]
        assert io.read_grey_raw(tmp_path / "left.png").dtype == np.uint16

    def test_exception(self, scene, tmp_path: Path) -> None:
        left, right, _ = scene
        missing = _invoke(left, tmp_path / "nowhere.png", "--out", tmp_path / "o")
        assert missing.exit_code == 2 and "nowhere.png" in missing.output and "does not exist" in missing.output
        narrow = tmp_path / "narrow.png"
        io.write_image(narrow, np.zeros((48, 120, 3), np.uint8))
        sizes = _invoke(left, narrow, "--out", tmp_path / "o")
        assert sizes.exit_code == 1
        assert "sizes differ: (48, 128) vs (48, 120)" in sizes.output and str(narrow) in sizes.output
        wide = _invoke(left, right, "--out", tmp_path / "o", "--max-disp", 200)
        assert wide.exit_code == 1 and "max_disp 200" in wide.output and str(left) in wide.output
        assert _invoke(left, right, "--out", tmp_path / "o", "--format", "jpg").exit_code == 2
        neither = _invoke("--out", tmp_path / "o")
        assert neither.exit_code == 2 and "LEFT RIGHT" in neither.output
        both = _invoke(left, right, "--dataset", "folder", "--root", tmp_path, "--out", tmp_path / "o")
        assert both.exit_code == 2 and "not both" in both.output
        assert not (tmp_path / "o").exists()
        (tmp_path / "a_file").write_text("")
        not_a_folder = _invoke(left, right, "--out", tmp_path / "a_file", "--max-disp", MAX_DISP)
        assert not_a_folder.exit_code == 1 and "a_file" in not_a_folder.output


class TestDataset:
    def test_feature(self, tmp_path: Path) -> None:
        """--dataset writes OUT/<frame id>.<ext>, each equal to dense's map of that pair; --jobs 2 changes nothing."""
        root = make_folder(tmp_path / "data", n=3, size=(32, 64))
        one = _invoke("--dataset", "folder", "--root", root, "--out", tmp_path / "one", "--max-disp", 16,
                      "--format", "npy", "--format", "pfm", "--quiet")
        assert one.exit_code == 0, one.output
        assert "wrote 3 pairs" in one.output
        two = _invoke("--dataset", "folder", "--root", root, "--out", tmp_path / "two", "--max-disp", 16,
                      "--format", "npy", "--jobs", 2, "--limit", 2)
        assert two.exit_code == 0, two.output
        assert sorted(p.name for p in (tmp_path / "two").iterdir()) == ["000.npy", "001.npy"]
        for i in range(3):
            left, right = io.read_image(root / f"left/{i:03d}.png"), io.read_image(root / f"right/{i:03d}.png")
            want = fill_rows_nearest(sgm_left(left, right, LabelerConfig(), 16)[0])
            np.testing.assert_array_equal(np.load(tmp_path / f"one/{i:03d}.npy"), want)
            np.testing.assert_array_equal(io.read_pfm(tmp_path / f"one/{i:03d}.pfm"), want)
            if i < 2:
                np.testing.assert_array_equal(np.load(tmp_path / f"two/{i:03d}.npy"), want)

    def test_search_range_from_calib(self, tmp_path: Path, shared_data: Path) -> None:
        """Without --max-disp a pair's own hint sets the range: MiddEval3 Motorcycle's calib.txt ndisp=70."""
        root = shared_data / "middlebury_eval3"
        result = _invoke("--dataset", "middlebury", "--root", root, "--out", tmp_path, "--format", "npy", "--quiet")
        assert result.exit_code == 0, result.output
        sample = load_pair(discover("middlebury", root)[0])
        assert sample.max_disp == 70
        want = fill_rows_nearest(sgm_left(sample.left, sample.right, LabelerConfig(), 70)[0])
        np.testing.assert_array_equal(np.load(tmp_path / "trainingQ-Motorcycle.npy"), want)

    def test_progress_bar(self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        """One bar over the pairs, advanced once per pair, named for the command."""
        seen: dict[str, object] = {"updates": 0}
        real = progress.progress_bar

        def spy(total: int, initial: int, quiet: bool, desc: str = "pvm-label") -> object:
            seen.update(total=total, desc=desc)
            bar = real(total, initial, quiet, desc)
            update = bar.update

            def counted(n: int = 1) -> object:
                seen["updates"] = int(seen["updates"]) + n  # type: ignore[call-overload]
                return update(n)

            bar.update = counted
            return bar

        monkeypatch.setattr(progress, "progress_bar", spy)
        root = make_folder(tmp_path / "data", n=2, size=(32, 64))
        done = match_dataset("folder", root, tmp_path / "out", max_disp=16, quiet=True)
        assert len(done) == 2 and seen == {"updates": 2, "total": 2, "desc": "pvm-label match"}

    def test_exception(self, tmp_path: Path) -> None:
        """A pair whose sizes differ is skipped, named with the file, and listed; the other pair is written."""
        root = make_folder(tmp_path / "data", n=2, size=(32, 64))
        io.write_image(root / "right/001.png", np.zeros((32, 60, 3), np.uint8))
        result = _invoke("--dataset", "folder", "--root", root, "--out", tmp_path / "out", "--max-disp", 16)
        assert result.exit_code == 1 and "sizes differ" in result.output and "right/001.png" in result.output
        assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["000.png", "failures.json"]
        missing = _invoke("--dataset", "kitti15", "--root", tmp_path / "nowhere", "--out", tmp_path / "out")
        assert missing.exit_code == 2 and "nowhere" in missing.output

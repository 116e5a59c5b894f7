"""`pvm-label` through click's CliRunner: both command forms, YAML config, verify, report and every bad input.

Labeling runs use the real PVM core on tiny random-texture pairs (64 x 128, K=2, max-disp 16) so each takes well
under a second after the JIT cache is warm.
"""

from __future__ import annotations

import json
import logging
import shutil
from contextlib import chdir
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from click.testing import CliRunner, Result
from conftest import SMALL, make_folder

from pvm_labeler.cli import main
from pvm_labeler.common.io import write_image
from pvm_labeler.shards import read_index


@pytest.fixture(scope="module", autouse=True)
def _needs_core() -> None:
    pytest.importorskip("pvm_labeler.sgm", reason="PVM core (pvm_labeler.sgm) not available yet")


@pytest.fixture(autouse=True)
def _reset_logging() -> None:
    # basicConfig() in the CLI is a no-op once a handler exists; make every test start clean.
    root = logging.getLogger()
    for handler in list(root.handlers):
        if not isinstance(handler, logging.NullHandler) and type(handler).__name__ != "LogCaptureHandler":
            root.removeHandler(handler)


def invoke(*args: str) -> Result:
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


class TestRun:
    def test_bare_form(self, tmp_path: Path) -> None:
        data, out = make_folder(tmp_path / "d"), tmp_path / "out"
        result = invoke("--dataset", "folder", "--root", data, "--out", out, *SMALL)
        assert result.exit_code == 0, result.output
        assert "labelled 3/3 pairs" in result.output and "bad-3" in result.output and "AEPE" in result.output
        assert read_index(out).num_samples == 3
        again = invoke("run", "--dataset", "folder", "--root", data, "--out", out, *SMALL)
        assert again.exit_code == 0 and "nothing to do: all 3 pairs" in again.output
        assert "(2 shards resumed" in again.output and "pairs/s" not in again.output
        assert invoke("verify", out).exit_code == 0

    def test_yaml_config_and_overrides(self, tmp_path: Path) -> None:
        data, out = make_folder(tmp_path / "d", n=1), tmp_path / "out"
        cfg = tmp_path / "labels.yaml"
        cfg.write_text(yaml.safe_dump({"dataset": "folder", "root": data.name, "k": 3, "kappa1": 0.7,
                                       "max_disp": 16, "labeler": {"census_window": 7}}))
        with chdir(tmp_path):  # paths as a user types them: relative
            result = invoke("run", "--config", cfg, "--k", "2", "--out", out.name, "--quiet")
        assert result.exit_code == 0, result.output
        resolved = yaml.safe_load((out / "config.yaml").read_text())
        assert resolved["labeler"]["k"] == 2  # flag beats YAML
        assert resolved["labeler"]["kappa1"] == 0.7 and resolved["labeler"]["census_window"] == 7
        assert read_index(out).config["census_window"] == 7
        # The resolved file is itself a valid --config: re-running from it resumes the same job, from any directory
        # (its paths are absolute: as typed, relative ones named nothing elsewhere).
        assert Path(resolved["root"]).is_absolute() and Path(resolved["out"]).is_absolute()
        (tmp_path / "elsewhere").mkdir()
        with chdir(tmp_path / "elsewhere"):
            again = invoke("run", "--config", out / "config.yaml", "--quiet")
        assert again.exit_code == 0 and "nothing to do: all 1 pair " in again.output
        assert "(1 shard resumed" in again.output

    def test_converted_images(self, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
        data, out = make_folder(tmp_path / "d", n=3), tmp_path / "out"
        left = cv2.imread(str(data / "left/000.png"))
        cv2.imwrite(str(data / "left/000.png"), cv2.cvtColor(left, cv2.COLOR_BGR2GRAY))  # grey
        right = cv2.imread(str(data / "right/001.png"))
        cv2.imwrite(str(data / "right/001.png"), cv2.cvtColor(right, cv2.COLOR_BGR2BGRA))  # RGBA
        cv2.imwrite(str(data / "left/002.png"), cv2.imread(str(data / "left/002.png")).astype(np.uint16) * 257)
        with caplog.at_level(logging.INFO, logger="pvm_labeler.common.io"):
            result = invoke("--dataset", "folder", "--root", data, "--out", out, *SMALL)
        assert result.exit_code == 0, result.output
        assert "000.png: grey image replicated to 3 channels" in caplog.text
        assert "001.png: RGBA image, alpha channel dropped" in caplog.text
        assert "002.png: 16-bit image scaled to 8 bit" in caplog.text


class TestBadInput:
    def test_unknown_dataset(self, tmp_path: Path) -> None:
        result = invoke("--dataset", "kitti2099", "--out", tmp_path / "o")
        assert result.exit_code == 2 and "kitti2099" in result.output
        assert not (tmp_path / "o").exists()

    def test_missing_root(self, tmp_path: Path) -> None:
        result = invoke("--dataset", "kitti15", "--root", tmp_path / "nowhere", "--out", tmp_path / "o")
        assert result.exit_code == 2 and "nowhere" in result.output and "does not exist" in result.output

    def test_root_without_pairs(self, tmp_path: Path) -> None:
        (tmp_path / "empty").mkdir()
        result = invoke("--dataset", "middlebury", "--root", tmp_path / "empty", "--out", tmp_path / "o")
        assert result.exit_code == 1 and "no stereo pairs found" in result.output
        assert not (tmp_path / "o").exists()

    def test_count_mismatch(self, tmp_path: Path) -> None:
        data = make_folder(tmp_path / "d")
        (data / "right/002.png").unlink()
        result = invoke("--dataset", "folder", "--root", data, "--out", tmp_path / "o", *SMALL)
        assert result.exit_code == 1 and "count mismatch: 3 images" in result.output
        assert not (tmp_path / "o").exists()

    def test_size_mismatch(self, tmp_path: Path) -> None:
        data = make_folder(tmp_path / "d")
        write_image(data / "right/001.png", np.zeros((64, 130, 3), np.uint8))
        result = invoke("--dataset", "folder", "--root", data, "--out", tmp_path / "o", *SMALL)
        assert result.exit_code == 1 and "sizes differ: (64, 128) vs (64, 130)" in result.output
        assert "right/001.png" in result.output and not (tmp_path / "o").exists()

    def test_too_small(self, tmp_path: Path) -> None:
        data = make_folder(tmp_path / "d", n=1, size=(32, 70))
        result = invoke("--dataset", "folder", "--root", data, "--out", tmp_path / "o", "--k", "6", "--max-disp", "64")
        assert result.exit_code == 1 and "too small for k=6 and max_disp=64" in result.output
        assert not (tmp_path / "o").exists()

    def test_yaml_beyond_kernel_limits_writes_nothing(self, tmp_path: Path) -> None:
        # census_window 9 used to pass pre-flight, write job.json and then fail in every worker
        data, out = make_folder(tmp_path / "d", n=1), tmp_path / "out"
        cfg = tmp_path / "labels.yaml"
        cfg.write_text(yaml.safe_dump({"dataset": "folder", "root": str(data), "max_disp": 16,
                                       "labeler": {"census_window": 9}}))
        result = invoke("run", "--config", cfg, "--out", out, "--k", "2", "--quiet")
        assert result.exit_code == 2, result.output
        assert "census_window must be one of (3, 5, 7)" in result.output and "got 9" in result.output
        assert not out.exists()

    def test_print_config(self, tmp_path: Path) -> None:
        cfg = tmp_path / "labels.yaml"
        cfg.write_text(yaml.safe_dump({"dataset": "sample", "kappa1": 0.7, "labeler": {"census_window": 7}}))
        out = tmp_path / "out"
        result = invoke("run", "--config", cfg, "--k", "3", "--out", out, "--print-config")
        assert result.exit_code == 0, result.output
        printed = yaml.safe_load(result.output)
        assert printed["dataset"] == "sample" and printed["out"] == str(out)
        assert printed["labeler"]["k"] == 3 and printed["labeler"]["kappa1"] == 0.7  # flag, then YAML
        assert printed["labeler"]["census_window"] == 7 and printed["labeler"]["max_disp"] == 64  # sample default
        assert not out.exists()  # nothing labelled, nothing written
        (tmp_path / "printed.yaml").write_text(result.output)  # the printout is itself a valid --config
        again = invoke("run", "--config", tmp_path / "printed.yaml", "--print-config")
        assert again.exit_code == 0 and yaml.safe_load(again.output) == printed

    def test_print_config_rejects_bad_values(self, tmp_path: Path) -> None:
        result = invoke("--dataset", "sample", "--out", tmp_path / "o", "--k", "1", "--print-config")
        assert result.exit_code == 2 and "--k must be >= 2" in result.output

    @pytest.mark.parametrize(
        ("args", "match"),
        [(["--k", "1"], "--k must be >= 2"), (["--kappa1", "-1"], "kappa1=-1.0"), (["--kappa2", "-0.1"], "kappa2=-0.1"),
         (["--jobs", "0"], "--jobs"), (["--backend", "mpi"], "mpi")],
    )
    def test_usage_errors(self, tmp_path: Path, args: list[str], match: str) -> None:
        result = invoke("--dataset", "sample", "--out", tmp_path / "o", *args)
        assert result.exit_code == 2, result.output
        assert match in result.output
        assert not (tmp_path / "o").exists()

    def test_out_not_writable(self, tmp_path: Path) -> None:
        (tmp_path / "f").write_text("a file")
        result = invoke("--dataset", "sample", "--out", tmp_path / "f" / "o", "--limit", "1", *SMALL)
        assert result.exit_code == 1 and "output dir not writable" in result.output

    def test_other_config_needs_overwrite(self, tmp_path: Path) -> None:
        data, out = make_folder(tmp_path / "d", n=1), tmp_path / "out"
        assert invoke("--dataset", "folder", "--root", data, "--out", out, *SMALL).exit_code == 0
        result = invoke("--dataset", "folder", "--root", data, "--out", out, *SMALL, "--kappa2", "0.2")
        assert result.exit_code == 1 and "different config" in result.output and "--overwrite" in result.output
        assert read_index(out).config["kappa2"] != 0.2
        result = invoke("--dataset", "folder", "--root", data, "--out", out, *SMALL, "--kappa2", "0.2", "--overwrite")
        assert result.exit_code == 0 and read_index(out).config["kappa2"] == 0.2

    def test_truncated_png_fails_one_pair(self, tmp_path: Path) -> None:
        data, out = make_folder(tmp_path / "d", n=3), tmp_path / "out"
        bad = data / "left/001.png"
        bad.write_bytes(bad.read_bytes()[:200])  # header intact, pixel data cut
        result = invoke("--dataset", "folder", "--root", data, "--out", out, *SMALL, "--shard-size", "2")
        assert result.exit_code == 1
        assert "1 pair FAILED" in result.output and "left/001.png" in result.output
        failures = json.loads((out / "failures.json").read_text())
        assert failures[0]["frame_id"] == "001" and "corrupt or truncated image" in failures[0]["error"]
        index = read_index(out)
        assert index.num_samples == 2 and [ids for _, ids in index.shards] == [["000"], ["002"]]
        assert not list(out.glob("*.tmp"))


class TestVerifyReport:
    def test_verify_broken(self, tmp_path: Path) -> None:
        data, out = make_folder(tmp_path / "d", n=2), tmp_path / "out"
        assert invoke("--dataset", "folder", "--root", data, "--out", out, *SMALL, "--shard-size", "1").exit_code == 0
        ok = invoke("verify", out)
        assert ok.exit_code == 0 and "ok: 2 samples in 2 shards" in ok.output
        shard = out / "shard-00001.h5"
        shard.write_bytes(shard.read_bytes()[:1500])
        result = invoke("verify", out)
        assert result.exit_code == 1 and "shard-00001.h5" in result.output and "shard-00000.h5" not in result.output

    def test_report(self, tmp_path: Path) -> None:
        data = make_folder(tmp_path / "d", n=2)
        runs = []
        for kappa1 in ("0.5", "2.0"):
            out = tmp_path / f"k{kappa1}"
            result = invoke("--dataset", "folder", "--root", data, "--out", out, *SMALL, "--kappa1", kappa1)
            assert result.exit_code == 0, result.output
            runs.append(out)
        result = invoke("report", *runs, "--out", tmp_path / "rep", "--pictures", "1")
        assert result.exit_code == 0, result.output
        assert "| 000 |" in result.output and "bad-3" in result.output
        doc = json.loads((tmp_path / "rep/report.json").read_text())
        assert len(doc["runs"]) == 2 and doc["runs"][0]["pooled"]["all"]["n_valid"] == 2 * 64 * 124
        assert (tmp_path / "rep/density_vs_error.png").stat().st_size > 1000
        assert sorted(p.name for p in (tmp_path / "rep/run00-k0.5").iterdir()) == ["000_error.png", "000_label.png"]

    def test_report_pictures_count_frames_without_gt_too(self, tmp_path: Path) -> None:
        """--pictures N: N frames per run; without GT each frame is one picture, and 2N frames were drawn."""
        data = make_folder(tmp_path / "d", n=3)
        shutil.rmtree(data / "gt")
        out = tmp_path / "k"
        assert invoke("--dataset", "folder", "--root", data, "--out", out, *SMALL).exit_code == 0
        result = invoke("report", out, "--out", tmp_path / "rep", "--pictures", "1")
        assert result.exit_code == 0, result.output
        assert [p.name for p in (tmp_path / "rep/run00-k").iterdir()] == ["000_label.png"]


def test_real_kitti_cli(tmp_path: Path, shared_data: Path) -> None:
    """Real data through the console entry: 2 KITTI frames, 2 workers, small K."""
    out = tmp_path / "kitti"
    result = invoke("--dataset", "kitti15", "--root", shared_data / "kitti15", "--out", out, "--limit", "2",
                    "--k", "2", "--max-disp", "96", "--jobs", "2", "--shard-size", "1", "--quiet")
    assert result.exit_code == 0, result.output
    assert "labelled 2/2 pairs" in result.output and "vs GT noc" in result.output
    assert invoke("verify", out).exit_code == 0
    m = json.loads((out / "index.json").read_text())["summary"]["metrics_noc"]
    # Loose but meaningful bars (the full KITTI quality bars are A2's test_kitti_quality): labels are semi-dense
    # and mostly right. First SGM version, K=2, D=96 on frames 000000/000001: see docs/labeling.md.
    assert 5 < m["density"] < 95, m
    assert m["bad3"] < 5.0 and m["epe"] < 1.5, m

"""From a user walkthrough of `pvm-label match` and `pvm-label pack-gt`: match takes run's dataset-reader options,
a pair that cannot be read is skipped (and listed) instead of aborting the batch, pack-gt has its own help and
errors, and its summary reports what a GT pack holds."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from click.testing import CliRunner, Result
from conftest import make_folder

from pvm_labeler.cli import main
from pvm_labeler.common import io
from pvm_labeler.job.summary import JobSummary


def _invoke(*args: object) -> Result:
    return CliRunner().invoke(main, [str(a) for a in args], prog_name="pvm-label")


def _options(command: str) -> set[str]:
    """The option names `pvm-label COMMAND --help` lists."""
    options = _invoke(command, "--help").output.split("\nOptions:\n")[1]
    return {word.strip(",") for line in options.splitlines() if line.lstrip().startswith("-")
            for word in line.split("  ")[1].split() if word.startswith("--")}


def _rig(root: Path, n: int = 3) -> Path:
    """A folder dataset whose views are not in the default folders: ROOT/cam0, ROOT/cam1, ROOT/disp."""
    make_folder(root, n=n, size=(32, 64))
    for old, new in (("left", "cam0"), ("right", "cam1"), ("gt", "disp")):
        (root / old).rename(root / new)
    return root


class TestMatchReaderOptions:
    def test_match_takes_run_reader_options(self, tmp_path: Path) -> None:
        """`match --dataset folder --left cam0 --right cam1 --gt disp` reads the rig as `run` would."""
        rig = _rig(tmp_path / "rig")
        result = _invoke("match", "--dataset", "folder", "--root", rig, "--left", "cam0", "--right", "cam1",
                         "--gt", "disp", "--out", tmp_path / "o", "--max-disp", 16, "--format", "npy", "--quiet")
        assert result.exit_code == 0, result.output
        assert "wrote 3 pairs" in result.output
        assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["000.npy", "001.npy", "002.npy"]
        reader = {"--left", "--right", "--gt", "--sceneflow-pass"}
        assert reader <= _options("match") and reader <= _options("run") and reader <= _options("pack-gt")

    def test_reader_options_need_a_dataset(self, tmp_path: Path) -> None:
        rig = _rig(tmp_path / "rig", n=1)
        result = _invoke("match", rig / "cam0/000.png", rig / "cam1/000.png", "--left", "cam0", "--out",
                         tmp_path / "o")
        assert result.exit_code == 2 and "--left" in result.output and "--dataset" in result.output
        assert not (tmp_path / "o").exists()


class TestMatchSkipsUnreadablePairs:
    def test_the_others_are_written_and_the_skipped_listed(self, tmp_path: Path) -> None:
        """A truncated image, a corrupt header and a size mismatch: each pair skipped with its reason in
        OUT/failures.json, the readable pair written, exit 1 naming the first; a clean re-run removes the list."""
        root = make_folder(tmp_path / "data", n=4, size=(32, 64))
        good = {name: (root / name).read_bytes() for name in ("left/000.png", "right/001.png", "left/002.png")}
        (root / "left/000.png").write_bytes(good["left/000.png"][: len(good["left/000.png"]) // 2])  # truncated
        (root / "right/001.png").write_bytes(b"not a png")  # unreadable header
        io.write_image(root / "left/002.png", np.zeros((32, 60, 3), np.uint8))  # sizes differ
        out = tmp_path / "out"
        args = ("match", "--dataset", "folder", "--root", root, "--out", out, "--max-disp", 16, "--format", "npy",
                "--quiet")
        result = _invoke(*args)
        assert result.exit_code == 1
        listed = out / "failures.json"
        assert ("3 of 4 pairs could not be read, e.g. 000: " in result.output
                and f"the other 1 was written; the list: {listed}" in result.output), result.output
        assert sorted(p.name for p in out.iterdir()) == ["003.npy", "failures.json"]
        failures = {f["frame_id"]: f["error"] for f in json.loads(listed.read_text())}  # the job's record form
        assert list(failures) == ["000", "001", "002"]
        assert "left/000.png" in failures["000"] and "right/001.png" in failures["001"]
        assert "sizes differ" in failures["002"]
        for name, data in good.items():
            (root / name).write_bytes(data)
        again = _invoke(*args)
        assert again.exit_code == 0 and "wrote 4 pairs" in again.output, again.output
        assert not listed.exists()


class TestPackGtCommand:
    def test_own_help(self) -> None:
        result = _invoke("pack-gt", "--help")
        assert result.exit_code == 0
        assert result.output.startswith("Usage: pvm-label pack-gt")
        assert "GT-only shards for supervised training" in " ".join(result.output.split())
        assert "Label a dataset" not in result.output
        options = _options("pack-gt")
        assert "--labels" not in options and "--kappa1" not in options and {"--dataset", "--out"} <= options
        assert "pack-gt" in _invoke("--help").output

    def test_errors_speak_of_pack_gt(self, tmp_path: Path) -> None:
        rig = _rig(tmp_path / "rig", n=2)
        result = _invoke("pack-gt", "--dataset", "folder", "--root", rig, "--left", "cam0", "--right", "cam1",
                         "--out", tmp_path / "o", "--quiet")
        assert result.exit_code == 1 and "pack-gt" in result.output and "2 of 2 pairs have none" in result.output
        assert "--labels none packs" not in result.output
        usage = _invoke("pack-gt", "--shard-size", 0)
        assert usage.exit_code == 2 and "Usage: pvm-label pack-gt" in usage.output

    def test_summary_reports_the_pack(self, tmp_path: Path) -> None:
        """Pairs packed and GT density, no label lines (0 %, NaN); a re-run prints 'nothing to do'."""
        out = tmp_path / "gt"
        first = _invoke("pack-gt", "--dataset", "sample", "--out", out, "--quiet")
        assert first.exit_code == 0, first.output
        assert first.output.startswith(f"packed 4/4 pairs (images + GT, no labels) into {out} ")
        assert "GT density: " in first.output and "label density" not in first.output
        assert "vs GT" not in first.output and "nan" not in first.output
        density = float(first.output.split("GT density: ")[1].split(" %")[0])
        assert 50 < density <= 100
        again = _invoke("pack-gt", "--dataset", "sample", "--out", out, "--quiet")
        assert again.exit_code == 0
        assert again.output.startswith(f"nothing to do: all 4 pairs in {out} were already packed (2 shards resumed")
        assert "pairs/s" not in again.output and "0 MiB" not in again.output and "nan" not in again.output


def test_a_summary_with_no_pair_worked_on_prints_no_speed() -> None:
    """No pair timed (NaN pairs/s, no worker): no '0.00 pairs/s, peak RSS per worker 0 MiB'."""
    summary = JobSummary(out="o", pairs_total=2, pairs_labeled=0, pairs_failed=2, shards_total=1, shards_written=0,
                         shards_resumed=0, seconds=0.0, pairs_per_s=math.nan, label_fraction=math.nan, metrics=None,
                         metrics_noc=None, peak_rss_mb_per_worker=0.0, cpu_seconds_per_pair=math.nan, parallel={},
                         failures=[{"frame_id": "a", "error": "x"}, {"frame_id": "b", "error": "y"}])
    text = summary.format()
    assert text.startswith("labelled 0/2 pairs into o (0 shards written, 0 resumed) in 0.0 s\n")
    assert "pairs/s" not in text and "MiB" not in text

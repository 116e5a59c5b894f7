"""A re-run retries the pairs that failed (the shard holding them is redone
atomically), `verify` lists failed pairs, a report without GT shows the densities, and the summary of a run with
nothing left to do says so. The labeler is a tiny deterministic fake (``JobSpec.label_fn``), the data a folder."""

from __future__ import annotations

import json
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner, Result
from conftest import make_folder

from pvm_labeler.cli import main
from pvm_labeler.common.datasets import discover, load_pair
from pvm_labeler.config import LabelerConfig
from pvm_labeler.job import FAILURES_FILE, JobSpec, run
from pvm_labeler.report import build_report
from pvm_labeler.shards import INDEX_NAME, open_shard, read_index, read_sample, verify, verify_shard

FAKE = f"{Path(__file__).stem}:fake_label"
CRASH_ENV = "PVM_TEST_FAKE_CRASH"  # the fake labeler dies (not a pair failure) on this frame id


def fake_label(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, frame_id: str) -> SimpleNamespace:
    """label = mean intensity / 8 on the right half, NaN on the left half (50 % density for even widths)."""
    if os.environ.get(CRASH_ENV) == frame_id:
        raise RuntimeError(f"simulated crash on {frame_id}")
    h, w = left.shape[:2]
    label = np.full((h, w), np.nan, np.float32)
    label[:, w // 2 :] = left[:, w // 2 :].mean(axis=2) / 8.0
    return SimpleNamespace(label=label, label_right=label[:, ::-1].copy(),
                           confidence=np.isfinite(label).astype(np.float32), eps=np.zeros(cfg.k),
                           factors=np.arange(1.0, cfg.k + 1), timings={"total": 0.0})


def _spec(root: Path, out: Path) -> JobSpec:
    return JobSpec(dataset="folder", root=root, out=out, config=LabelerConfig(k=2, max_disp=16), shard_size=2,
                   quiet=True, label_fn=FAKE)


def _corrupt(path: Path) -> bytes:
    """Cut ``path`` to its first 200 bytes (header intact, pixels gone); returns the original bytes."""
    original = path.read_bytes()
    path.write_bytes(original[:200])
    return original


def _shard_ids(out: Path) -> list[list[str]]:
    return [ids for _, ids in read_index(out).shards]


def invoke(*args: object) -> Result:
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture
def failed_run(tmp_path: Path) -> tuple[Path, Path, bytes]:
    """Folder 000..002 whose left/001.png is truncated, labelled once: shard 0 = [000] + 001 failed, shard 1 =
    [002]. Returns (data root, out, the good bytes of left/001.png)."""
    data, out = make_folder(tmp_path / "d", n=3), tmp_path / "out"
    good = _corrupt(data / "left/001.png")
    summary = run(_spec(data, out))
    assert summary.pairs_failed == 1 and _shard_ids(out) == [["000"], ["002"]]
    assert [f["frame_id"] for f in json.loads((out / FAILURES_FILE).read_text())] == ["001"]
    return data, out, good


class TestRetry:
    def test_fixed_pair_is_labelled_on_rerun(self, failed_run: tuple[Path, Path, bytes]) -> None:
        data, out, good = failed_run
        (data / "left/001.png").write_bytes(good)
        kept = (out / "shard-00001.h5").stat().st_mtime_ns
        summary = run(_spec(data, out))
        assert (summary.pairs_labeled, summary.pairs_failed) == (3, 0)
        assert (summary.shards_written, summary.shards_resumed) == (1, 1)
        assert _shard_ids(out) == [["000", "001"], ["002"]] and verify(out) == []
        assert not (out / FAILURES_FILE).exists()  # the pair that now succeeds left it
        assert (out / "shard-00001.h5").stat().st_mtime_ns == kept  # the shard without failures was resumed
        pair = load_pair(next(r for r in discover("folder", data) if r.frame_id == "001"))
        expected = np.full((64, 128), np.nan, np.float32)
        expected[:, 64:] = pair.left[:, 64:].mean(axis=2) / 8.0
        with open_shard(out / "shard-00000.h5") as h5:
            np.testing.assert_array_equal(read_sample(h5, "001").label, expected)
        assert "1 pair FAILED" not in summary.format()

    def test_pair_still_bad_stays_recorded(self, failed_run: tuple[Path, Path, bytes]) -> None:
        data, out, _ = failed_run
        summary = run(_spec(data, out))
        assert (summary.pairs_labeled, summary.pairs_failed, summary.shards_written) == (2, 1, 1)
        failures = json.loads((out / FAILURES_FILE).read_text())
        assert [f["frame_id"] for f in failures] == ["001"] and "corrupt or truncated" in failures[0]["error"]
        assert _shard_ids(out) == [["000"], ["002"]] and verify(out) == []
        assert "1 pair FAILED" in summary.format() and "re-run retries" in summary.format()

    def test_interrupted_retry_keeps_the_old_shard(self, failed_run: tuple[Path, Path, bytes],
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
        data, out, good = failed_run
        (data / "left/001.png").write_bytes(good)
        before = (out / "shard-00000.h5").read_bytes()
        monkeypatch.setenv(CRASH_ENV, "001")  # the retry dies after 000 went into shard-00000.h5.tmp
        with pytest.raises(RuntimeError, match="simulated crash"):
            run(_spec(data, out))
        assert (out / "shard-00000.h5").read_bytes() == before  # still the old, valid shard
        assert verify_shard(out / "shard-00000.h5", ["000"], None) == []
        assert not list(out.glob("*.tmp")) and not (out / INDEX_NAME).exists()  # nothing looks complete
        monkeypatch.delenv(CRASH_ENV)
        assert run(_spec(data, out)).pairs_labeled == 3 and _shard_ids(out) == [["000", "001"], ["002"]]

    def test_retry_where_every_pair_fails_removes_the_old_shard(self, failed_run: tuple[Path, Path, bytes]) -> None:
        data, out, _ = failed_run
        _corrupt(data / "left/000.png")
        summary = run(_spec(data, out))
        assert (summary.pairs_labeled, summary.pairs_failed) == (1, 2)
        assert not (out / "shard-00000.h5").exists()  # its old content (000's label) is not this run's
        assert _shard_ids(out) == [["002"]] and verify(out) == []
        assert [f["frame_id"] for f in json.loads((out / FAILURES_FILE).read_text())] == ["000", "001"]


class TestVerify:
    def test_lists_failed_pairs_and_exits_0(self, failed_run: tuple[Path, Path, bytes]) -> None:
        _, out, _ = failed_run
        result = invoke("verify", out)
        assert result.exit_code == 0, result.output
        assert "ok: 2 samples in 2 shards" in result.output
        assert f"1 of 3 pairs failed to label: see {out / FAILURES_FILE}" in result.output
        assert "  001: " in result.output and "corrupt or truncated" in result.output

    def test_no_failures_no_line(self, tmp_path: Path) -> None:
        data, out = make_folder(tmp_path / "d", n=1), tmp_path / "out"
        run(_spec(data, out))
        result = invoke("verify", out)
        assert result.exit_code == 0 and "ok: 1 sample in 1 shard," in result.output
        assert "failed" not in result.output

    def test_unreadable_failures_file(self, failed_run: tuple[Path, Path, bytes]) -> None:
        _, out, _ = failed_run
        (out / FAILURES_FILE).write_text("{not json")
        result = invoke("verify", out)
        assert result.exit_code == 1 and str(out / FAILURES_FILE) in result.output and "unreadable" in result.output

    def test_one_problem_in_the_singular(self, failed_run: tuple[Path, Path, bytes]) -> None:
        _, out, _ = failed_run
        (out / "shard-00001.h5").write_bytes(b"not hdf5")
        result = invoke("verify", out)
        assert result.exit_code == 1 and "1 problem in " in result.output and "1 problems" not in result.output


def test_report_without_gt_shows_densities(tmp_path: Path) -> None:
    data, out = make_folder(tmp_path / "d", n=2), tmp_path / "out"
    for gt in (data / "gt").iterdir():
        gt.unlink()
    (data / "gt").rmdir()
    run(_spec(data, out))
    result = build_report([out], tmp_path / "rep", pictures=0)
    text = (tmp_path / "rep/report.md").read_text()
    assert result["runs"][0]["pooled"] == {}
    # The fake labels the right half of each 64 x 128 frame: 50.0 % of all pixels, pooled and per frame.
    assert "| out (k1=2.0, k2=0.3) | (no GT) | - | 50.0 | - |" in text
    assert "| 000 (no GT) | - | 50.0 | - |" in text and "| 001 (no GT) | - | 50.0 | - |" in text


def test_nothing_to_do_summary(tmp_path: Path) -> None:
    data, out = make_folder(tmp_path / "d", n=3), tmp_path / "out"
    first = run(_spec(data, out)).format()
    assert first.startswith("labelled 3/3 pairs into") and "(2 shards written, 0 resumed)" in first
    again = run(_spec(data, out)).format()
    assert again.startswith(f"nothing to do: all 3 pairs in {out} were already labelled (2 shards resumed")
    assert "pairs/s" not in again and "0 MiB" not in again


def test_throughput_counts_labelled_pairs_only(tmp_path: Path) -> None:
    """Every pair failing printed "labelled 0/3 pairs ... (3.55 pairs/s ...)": failed pairs are no throughput."""
    data, out = make_folder(tmp_path / "d", n=3), tmp_path / "out"
    for name in ("000", "001", "002"):
        _corrupt(data / f"left/{name}.png")
    summary = run(_spec(data, out))
    assert summary.pairs_labeled == 0 and summary.pairs_failed == 3
    assert summary.pairs_per_s == 0 and "pairs/s" not in summary.format()


@pytest.mark.parametrize("compression", ["blosc-lz4", "lzf", "none"])
def test_damaged_bytes_inside_a_shard_are_found(tmp_path: Path, compression: str) -> None:
    """Bytes flipped inside an array's data read back as other values and `verify` said ok (a right image off by up
    to 230 grey levels): every array carries a fletcher32 checksum now, so verify names the sample and a resumed job
    relabels the shard."""
    import h5py

    data, out = make_folder(tmp_path / "d", n=2), tmp_path / "out"
    spec = JobSpec(**{**vars(_spec(data, out)), "compression": compression})
    run(spec)
    path, ids = read_index(out).shards[0]
    with h5py.File(path) as h5:
        info = h5[ids[0]]["right"].id.get_chunk_info(0)
    raw = bytearray(path.read_bytes())
    for i in range(info.byte_offset + info.size // 2, info.byte_offset + info.size // 2 + 16):
        raw[i] ^= 0xFF
    path.write_bytes(bytes(raw))
    problems = verify(out)
    assert len(problems) == 1 and f"sample '{ids[0]}' is unreadable" in problems[0] and "damaged" in problems[0]
    again = run(spec)
    assert again.shards_written == 1 and verify(out) == []

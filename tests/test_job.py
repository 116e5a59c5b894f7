"""The labeling job: shard plan, resume, failures, bad input, parallel invariance, Dask, SIGKILL resume.

Job mechanics (resume, failures, config checks) use a tiny deterministic fake labeler injected through
``JobSpec.label_fn`` so they run in well under a second; parallel invariance, Dask, the SIGKILL resume and the
real-data run use the real PVM core on small inputs (synthetic pairs, small K / max_disp, two KITTI frames).
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from pvm_labeler.common.datasets import discover, load_pair
from pvm_labeler.common.errors import ConfigError, InputError
from pvm_labeler.common.io import read_image, write_image
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.config import LabelerConfig
from pvm_labeler.job import FAILURES_FILE, JOB_FILE, JobSpec, ShardTask, longest_first, predicted_work, run
from pvm_labeler.multiscale import draw_eps, scale_geometry
from pvm_labeler.parallel import numba_threads_per_worker, thread_budget
from pvm_labeler.report import build_report
from pvm_labeler.shards import INDEX_NAME, open_shard, read_index, read_sample, verify

REPO = Path(__file__).resolve().parents[1]
FAKE = f"{Path(__file__).stem}:fake_label"


def fake_label(left: np.ndarray, right: np.ndarray, cfg: LabelerConfig, frame_id: str) -> SimpleNamespace:
    """Deterministic stand-in for label_pair: label = mean intensity / 8 on the right half, NaN elsewhere."""
    if frame_id == "synthetic-001" and cfg.extra.get("fail_one"):
        raise InputError(f"fake failure for {frame_id}")
    h, w = left.shape[:2]
    label = np.full((h, w), np.nan, np.float32)
    label[:, w // 2 :] = left[:, w // 2 :].mean(axis=2) / 8.0 + cfg.kappa1
    return SimpleNamespace(label=label, label_right=label[:, ::-1].copy(),
                           confidence=np.isfinite(label).astype(np.float32), eps=np.zeros(cfg.k),
                           factors=np.arange(1.0, cfg.k + 1), timings={"total": 0.0})


def _spec(out: Path, **kwargs: object) -> JobSpec:
    base = {"dataset": "sample", "root": None, "out": out, "config": LabelerConfig(k=2, max_disp=64),
            "shard_size": 2, "quiet": True, "label_fn": FAKE}
    base.update(kwargs)
    return JobSpec(**base)


def _all_samples(out: Path) -> dict[str, object]:
    index = read_index(out)
    samples = {}
    for path, ids in index.shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                samples[frame_id] = read_sample(h5, frame_id)
    return samples


def _assert_same_shards(a: Path, b: Path) -> None:
    sa, sb = _all_samples(a), _all_samples(b)
    assert list(sa) == list(sb)
    for frame_id in sa:
        for name in ("left", "right", "label", "label_right", "confidence", "gt", "gt_noc", "gt_right"):
            x, y = getattr(sa[frame_id], name), getattr(sb[frame_id], name)
            assert (x is None) == (y is None), (frame_id, name)
            if x is not None:
                np.testing.assert_array_equal(x, y, err_msg=f"{frame_id}/{name}")


class TestJobMechanics:
    def test_smoke(self, tmp_path: Path) -> None:
        out = tmp_path / "labels"
        summary = run(_spec(out))
        assert summary.pairs_total == summary.pairs_labeled == 4 and summary.shards_written == 2
        assert verify(out) == []
        assert {p.name for p in out.iterdir()} == {"index.json", "job.json", "config.yaml", "shard-00000.h5",
                                                   "shard-00001.h5"}
        samples = _all_samples(out)
        acc = MetricAccumulator()
        for ref in discover("sample", None):
            pair = load_pair(ref)
            expected = fake_label(pair.left, pair.right, LabelerConfig(k=2, max_disp=64), ref.frame_id)
            np.testing.assert_array_equal(samples[ref.frame_id].label, expected.label)
            np.testing.assert_array_equal(samples[ref.frame_id].left, pair.left)
            acc.update(expected.label, pair.gt)
            assert samples[ref.frame_id].attrs["sources"]
        assert summary.metrics == pytest.approx(acc.compute())
        assert summary.label_fraction == pytest.approx(50.0, abs=0.2)
        index = json.loads((out / INDEX_NAME).read_text())
        assert index["dataset"]["name"] == "sample" and index["config"]["k"] == 2

    def test_resume_relabels_only_missing(self, tmp_path: Path) -> None:
        out, ref_out = tmp_path / "a", tmp_path / "ref"
        run(_spec(ref_out))
        run(_spec(out))
        stamp = (out / "shard-00000.h5").stat().st_mtime_ns
        (out / "shard-00001.h5").unlink()
        (out / "shard-00001.h5.tmp").write_bytes(b"half written")
        summary = run(_spec(out))
        assert summary.shards_written == 1 and summary.shards_resumed == 1
        assert (out / "shard-00000.h5").stat().st_mtime_ns == stamp
        assert not (out / "shard-00001.h5.tmp").exists() and verify(out) == []
        _assert_same_shards(out, ref_out)

    def test_resume_relabels_a_shard_whose_image_changed(self, tmp_path: Path,
                                                         caplog: pytest.LogCaptureFixture) -> None:
        """An image replaced under the same name (re-exported, re-rectified) is seen by a resume: its shard is
        relabelled from the new bytes, the other shard is kept as it was."""
        from conftest import make_folder

        root, out = make_folder(tmp_path / "pairs", n=4), tmp_path / "a"
        spec = {"dataset": "folder", "root": root}
        run(_spec(out, **spec))
        stamp = (out / "shard-00000.h5").stat().st_mtime_ns
        before = _all_samples(out)["002"].label
        image = root / "left" / "002.png"
        write_image(image, np.full_like(read_image(image), 200))
        with caplog.at_level(logging.WARNING):
            summary = run(_spec(out, **spec))
        assert summary.shards_written == 1 and summary.shards_resumed == 1
        assert "the files of 1 pair changed since it was labelled (002)" in caplog.text
        assert (out / "shard-00000.h5").stat().st_mtime_ns == stamp and verify(out) == []
        after = _all_samples(out)["002"].label
        expected = 200 / 8.0 + LabelerConfig().kappa1  # fake_label's value from the new image
        assert np.nanmax(np.abs(after - expected)) < 1e-4 and np.nanmax(np.abs(before - expected)) > 1

    def test_limit_grows_and_shrinks(self, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
        out = tmp_path / "a"
        first = run(_spec(out, limit=2))
        assert first.shards_written == 1
        grown = run(_spec(out))  # the full dataset continues after the quick --limit 2 run
        assert grown.shards_resumed == 1 and grown.shards_written == 1 and read_index(out).num_samples == 4
        _assert_same_shards(out, self._reference(tmp_path))
        with caplog.at_level(logging.WARNING):
            shrunk = run(_spec(out, limit=2))
        assert shrunk.shards_resumed == 1 and read_index(out).num_samples == 2
        assert sorted(p.name for p in out.glob("shard-*")) == ["shard-00000.h5"] and verify(out) == []
        assert "removing 1 labelled shard(s)" in caplog.text and "shard-00001.h5" in caplog.text  # it was silent

    def _reference(self, tmp_path: Path) -> Path:
        run(_spec(tmp_path / "ref"))
        return tmp_path / "ref"

    def test_resume_replaces_corrupt_shard(self, tmp_path: Path) -> None:
        out = tmp_path / "a"
        run(_spec(out))
        path = out / "shard-00001.h5"
        path.write_bytes(path.read_bytes()[:2000])
        summary = run(_spec(out))
        assert summary.shards_written == 1 and verify(out) == []

    def test_different_config_needs_overwrite(self, tmp_path: Path) -> None:
        out = tmp_path / "a"
        run(_spec(out))
        before = sorted(p.name for p in out.iterdir())
        old_kappa1 = LabelerConfig().kappa1  # the PVM core's measured default
        new_kappa1 = old_kappa1 + 0.5
        match = rf"different config/dataset \(config.kappa1: {old_kappa1} -> {new_kappa1}\).*--overwrite"
        with pytest.raises(InputError, match=match):
            run(_spec(out, config=LabelerConfig(k=2, max_disp=64, kappa1=new_kappa1)))
        assert sorted(p.name for p in out.iterdir()) == before
        build_report([out], out / "report", pictures=1)  # `pvm-label report DIR`'s default folder
        (out / "report" / "notes.txt").write_text("the user's own file")
        summary = run(_spec(out, config=LabelerConfig(k=2, max_disp=64, kappa1=new_kappa1), overwrite=True))
        assert summary.shards_written == 2 and read_index(out).config["kappa1"] == new_kappa1
        # the earlier labels' report went with them (it would describe the new labels wrongly); nothing else did
        assert [p.name for p in (out / "report").rglob("*")] == ["notes.txt"]

    def test_a_job_from_before_a_new_config_field_still_resumes(self, tmp_path: Path) -> None:
        """job.json written before c2_scale existed: the field's default reproduces those labels, so no error."""
        out = tmp_path / "a"
        run(_spec(out))
        doc = json.loads((out / "job.json").read_text())
        del doc["config"]["c2_scale"]
        (out / "job.json").write_text(json.dumps(doc))
        summary = run(_spec(out))
        assert summary.shards_written + summary.shards_resumed == 2 and verify(out) == []

    def test_other_compression_names_the_option(self, tmp_path: Path) -> None:
        # shards of an older default compression: the error says how to continue them, and that works
        out = tmp_path / "out"
        run(_spec(out, compression="lzf"))
        match = r'compression: "lzf" -> "blosc-lz4"\).*--compression lzf to continue them'
        with pytest.raises(InputError, match=match):
            run(_spec(out))
        assert run(_spec(out, compression="lzf")).shards_resumed == 2

    def test_a_plan_without_shards_is_no_conflict(self, tmp_path: Path) -> None:
        """A run that stopped after writing job.json/config.yaml but before any shard (an unreachable Dask
        scheduler) leaves nothing to protect: a run with other settings starts without --overwrite."""
        out = tmp_path / "a"
        run(_spec(out))
        for path in out.glob("shard-*"):
            path.unlink()
        (out / INDEX_NAME).unlink()
        summary = run(_spec(out, config=LabelerConfig(k=2, max_disp=64, kappa1=3.0)))
        assert summary.shards_written == 2 and json.loads((out / JOB_FILE).read_text())["config"]["kappa1"] == 3.0

    def test_unknown_shards_need_overwrite(self, tmp_path: Path) -> None:
        out = tmp_path / "a"
        run(_spec(out))
        (out / JOB_FILE).unlink()
        with pytest.raises(InputError, match="unknown run"):
            run(_spec(out))

    def test_pair_failure_recorded(self, tmp_path: Path) -> None:
        out = tmp_path / "a"
        summary = run(_spec(out, config=LabelerConfig(k=2, max_disp=64, extra={"fail_one": True})))
        assert summary.pairs_failed == 1 and summary.pairs_labeled == 3
        failures = json.loads((out / FAILURES_FILE).read_text())
        assert failures[0]["frame_id"] == "synthetic-001" and "fake failure" in failures[0]["error"]
        assert read_index(out).shards[0][1] == ["motorcycle", "synthetic-000"]
        assert read_index(out).shards[1][1] == ["synthetic-002"]
        assert verify(out) == []

    @pytest.mark.slow
    def test_limit_and_loky_workers(self, tmp_path: Path) -> None:
        # The fake lives in this test module: loky workers import it through the parent's sys.path.
        out = tmp_path / "a"
        summary = run(_spec(out, limit=3, shard_size=1, jobs=2))
        assert summary.pairs_labeled == 3 and summary.shards_written == 3
        single = tmp_path / "b"
        run(_spec(single, limit=3, shard_size=1, jobs=1))
        _assert_same_shards(out, single)


class _Bar:
    """Stands in for the tqdm bar (which is off when stderr is not a TTY, as under pytest)."""

    def __init__(self, total: int, initial: int) -> None:
        self.total, self.n, self.updates, self.disable, self.closed = total, initial, [], False, False

    def update(self, k: int) -> None:
        self.n += k
        self.updates.append(k)

    def set_postfix(self, **_: object) -> None:
        pass

    def close(self) -> None:
        self.closed = True


class TestProgress:
    @pytest.mark.parametrize("jobs", [1, pytest.param(2, marks=pytest.mark.slow)])
    def test_bar_advances_per_pair(self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, jobs: int) -> None:
        bars: list[_Bar] = []
        monkeypatch.setattr("pvm_labeler.job.runner.progress_bar",
                            lambda total, initial, quiet: bars.append(_Bar(total, initial)) or bars[-1])
        run(_spec(tmp_path / "a", shard_size=3, jobs=jobs, quiet=False))
        (bar,) = bars
        assert bar.updates == [1, 1, 1, 1] and bar.n == bar.total == 4 and bar.closed
        # Resumed shards count as done from the start.
        (tmp_path / "a/shard-00001.h5").unlink()
        run(_spec(tmp_path / "a", shard_size=3, jobs=jobs, quiet=False))
        assert bars[1].updates == [1] and bars[1].n == 4


class TestScheduling:
    def test_predicted_work_hand_computed(self) -> None:
        # K = 2: the full-resolution term H * W * D plus the k = 2 scale at the frame's own random factor
        cfg = LabelerConfig(k=2, max_disp=64)
        eps = draw_eps(cfg.seed, "f7", 2)[1]
        w2 = round(400 / (2 + eps))
        h2 = round(100 / (2 + eps))
        d2 = math.ceil(64 / (400 / w2) - 1e-9)
        geometry = scale_geometry(100, 400, draw_eps(cfg.seed, "f7", 2), cfg.max_disp)
        assert predicted_work(geometry) == 100 * 400 * 64 + h2 * w2 * d2

    def test_longest_first(self) -> None:
        cfg = LabelerConfig(k=6, max_disp=64)
        sizes = {f"f{i}": (100, 400) for i in range(12)} | {"big": (200, 800)}
        tasks = [ShardTask(i, f"s{i}", [SimpleNamespace(frame_id=fid)], {}, "none", 1)
                 for i, fid in enumerate(sizes)]
        per_frame = {fid: predicted_work(scale_geometry(*sizes[fid], draw_eps(cfg.seed, fid, cfg.k), cfg.max_disp))
                     for fid in sizes}
        order = [task.refs[0].frame_id for task in longest_first(tasks, per_frame)]
        work = [per_frame[fid] for fid in order]
        assert order[0] == "big" and work == sorted(work, reverse=True)
        assert len(set(work)) > 3  # the random factors really make equal-size pairs differ


class TestThreadBudget:
    def test_workers_times_threads_within_cores(self) -> None:
        assert numba_threads_per_worker(1, cores=2) == 2
        assert numba_threads_per_worker(2, cores=2) == 1
        assert numba_threads_per_worker(3, cores=2) == 1  # never 0
        assert numba_threads_per_worker(2, cores=8) == 4

    def test_set_and_restore(self) -> None:
        import cv2
        import numba

        before = (numba.get_num_threads(), cv2.getNumThreads())
        with thread_budget(1):
            assert numba.get_num_threads() == 1 and cv2.getNumThreads() == 1
        assert (numba.get_num_threads(), cv2.getNumThreads()) == before


class TestBadInput:
    def _folder(self, root: Path, sizes: list[tuple[tuple[int, int], tuple[int, int]]]) -> None:
        for view in ("left", "right"):
            (root / view).mkdir(parents=True)
        rng = np.random.default_rng(0)
        for i, (left_hw, right_hw) in enumerate(sizes):
            write_image(root / "left" / f"{i:03d}.png", rng.integers(0, 255, (*left_hw, 3), dtype=np.uint8))
            write_image(root / "right" / f"{i:03d}.png", rng.integers(0, 255, (*right_hw, 3), dtype=np.uint8))

    def test_size_mismatch_nothing_written(self, tmp_path: Path) -> None:
        self._folder(tmp_path / "d", [((200, 300), (200, 300)), ((200, 300), (200, 302))])
        out = tmp_path / "out"
        match = (r"(?s)1 of 2 pairs are unusable.*--skip-unusable labels the others.*001: left/right sizes differ"
                 r".*right/001.png")
        with pytest.raises(InputError, match=match):
            run(_spec(out, dataset="folder", root=tmp_path / "d"))
        assert not out.exists()

    def test_skip_unusable_labels_the_others_and_lists_them(self, tmp_path: Path) -> None:
        """--skip-unusable: the two unusable pairs (sizes differ; an unreadable file) are left out, listed in
        failures.json and the summary (exit 1 at the CLI), the three others labelled; the pairs' count holds all
        five. A re-run after the files are mended labels them (failures.json removed)."""
        root = tmp_path / "d"
        self._folder(root, [((200, 300), (200, 300))] * 3 + [((200, 300), (200, 302)), ((200, 300), (200, 300))])
        good = (root / "right" / "004.png").read_bytes()
        (root / "right" / "004.png").write_bytes(b"not a png")
        out = tmp_path / "out"
        summary = run(_spec(out, dataset="folder", root=root, skip_unusable=True))
        assert summary.pairs_total == 5 and summary.pairs_labeled == 3 and summary.pairs_failed == 2
        failures = json.loads((out / FAILURES_FILE).read_text())
        assert [(f["frame_id"], f["stage"]) for f in failures] == [("003", "preflight"), ("004", "preflight")]
        assert "sizes differ" in failures[0]["error"] and "right/004.png" in failures[1]["error"]
        assert sorted(i for _, ids in read_index(out).shards for i in ids) == ["000", "001", "002"]
        assert "2 pairs FAILED" in summary.format() and "003: left/right sizes differ" in summary.format()
        write_image(root / "right" / "003.png", read_image(root / "left" / "003.png"))  # mended
        (root / "right" / "004.png").write_bytes(good)
        again = run(_spec(out, dataset="folder", root=root, skip_unusable=True))
        assert again.pairs_labeled == 5 and not again.failures and not (out / FAILURES_FILE).exists()

    def test_skip_unusable_with_no_usable_pair_writes_nothing(self, tmp_path: Path) -> None:
        self._folder(tmp_path / "d", [((200, 300), (200, 302))])
        with pytest.raises(InputError, match=r"1 of 1 pairs are unusable \(nothing was written\)"):
            run(_spec(tmp_path / "out", dataset="folder", root=tmp_path / "d", skip_unusable=True))
        assert not (tmp_path / "out").exists()

    def test_image_too_small(self, tmp_path: Path) -> None:
        self._folder(tmp_path / "d", [((40, 60), (40, 60))])
        with pytest.raises(InputError, match=r"000: image 60x40 too small for k=6 and max_disp=48"):
            run(_spec(tmp_path / "out", dataset="folder", root=tmp_path / "d",
                      config=LabelerConfig(k=6, max_disp=48)))
        assert not (tmp_path / "out").exists()

    def test_search_range_too_small_for_k(self, tmp_path: Path) -> None:
        # max_disp 4 at K = 6: the coarsest scales would search a single disparity, which the SGM cannot take
        self._folder(tmp_path / "d", [((200, 300), (200, 300))])
        with pytest.raises(InputError, match=r"000: max_disp=4 too small for k=6: scale \d .* would search 1 disp"):
            run(_spec(tmp_path / "out", dataset="folder", root=tmp_path / "d", config=LabelerConfig(k=6, max_disp=4)))
        assert not (tmp_path / "out").exists()

    def test_out_not_writable(self, tmp_path: Path) -> None:
        (tmp_path / "file").write_text("x")
        with pytest.raises(InputError, match="output dir not writable: --out .*file/labels"):
            run(_spec(tmp_path / "file" / "labels"))

    @pytest.mark.parametrize(
        ("config", "match"),
        [
            (LabelerConfig(k=1), r"--k must be >= 2.*got 1"),
            (LabelerConfig(kappa1=-0.5), "kappa1=-0.5"),
            (LabelerConfig(kappa2=-1.0), "kappa2=-1.0"),
            (LabelerConfig(census_window=9), r"census_window must be one of \(3, 5, 7\)"),
            (LabelerConfig(p2=9000), "overflows the uint16 cost sum"),
        ],
    )
    def test_config(self, tmp_path: Path, config: LabelerConfig, match: str) -> None:
        with pytest.raises(ConfigError, match=match):
            run(_spec(tmp_path / "out", config=config))
        assert not (tmp_path / "out").exists()

    def test_options(self, tmp_path: Path) -> None:
        with pytest.raises(ConfigError, match="unknown dataset 'nope'"):
            run(_spec(tmp_path, dataset="nope"))
        with pytest.raises(ConfigError, match="--scheduler needs --backend dask"):
            run(_spec(tmp_path, scheduler="tcp://x:1"))
        with pytest.raises(ConfigError, match="--shard-size must be >= 1"):
            run(_spec(tmp_path, shard_size=0))


# --------------------------------------------------------------------------------------- real PVM core below
REAL = LabelerConfig(k=3, max_disp=48)


def _real_spec(out: Path, **kwargs: object) -> JobSpec:
    # The three synthetic pairs (224..256 x 304..336) label in a fraction of a second each with K=3.
    base = {"dataset": "sample", "root": None, "out": out, "config": REAL, "shard_size": 1, "quiet": True,
            "dataset_options": {"motorcycle": False}}
    base.update(kwargs)
    return JobSpec(**base)


@pytest.fixture(scope="module")
def real_labeler() -> None:
    pytest.importorskip("pvm_labeler.sgm", reason="PVM core (pvm_labeler.sgm) not available yet")


def test_two_workers_leave_labels_unchanged(tmp_path: Path, real_labeler: None) -> None:
    """--jobs 2 (threads, one numba thread each): the shards equal the --jobs 1 run."""
    run(_real_spec(tmp_path / "jobs1"))
    run(_real_spec(tmp_path / "threads2", jobs=2, backend="threading", numba_threads=1))
    _assert_same_shards(tmp_path / "jobs1", tmp_path / "threads2")


@pytest.mark.slow
@pytest.mark.faults
class TestRealLabeler:
    def test_jobs_and_backends_identical(self, tmp_path: Path, real_labeler: None) -> None:
        base = tmp_path / "jobs1"
        s1 = run(_real_spec(base))
        assert s1.pairs_labeled == 3 and 0 < s1.label_fraction < 100
        for name, kwargs in (("loky2", {"jobs": 2}), ("thread2", {"jobs": 2, "backend": "threading"})):
            run(_real_spec(tmp_path / name, **kwargs))
            _assert_same_shards(base, tmp_path / name)

    def test_dask_local_cluster(self, tmp_path: Path, real_labeler: None) -> None:
        distributed = pytest.importorskip("distributed")
        run(_real_spec(tmp_path / "loky", jobs=2))
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                      dashboard_address=None) as cluster:
            summary = run(_real_spec(tmp_path / "dask", backend="dask", scheduler=cluster.scheduler_address))
        assert summary.pairs_labeled == 3
        _assert_same_shards(tmp_path / "loky", tmp_path / "dask")

    def test_sigkill_resume(self, tmp_path: Path, real_labeler: None) -> None:
        ref_out, out = tmp_path / "ref", tmp_path / "killed"
        run(_real_spec(ref_out, dataset_options={}))  # all 4 sample pairs, like the CLI run below
        cmd = [sys.executable, "-m", "pvm_labeler.cli", "run", "--dataset", "sample", "--out", str(out),
               "--k", str(REAL.k), "--max-disp", str(REAL.max_disp), "--shard-size", "1", "--quiet"]
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        first = out / "shard-00000.h5"
        deadline = time.monotonic() + 300
        while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        done_before = sorted(p.name for p in out.glob("shard-*.h5"))
        assert not (out / INDEX_NAME).exists(), "killed before the end: there must be no index yet"
        assert 1 <= len(done_before) < 4, done_before
        result = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, result.stderr
        assert f"{len(done_before)} resumed" in result.stdout
        assert verify(out) == []
        _assert_same_shards(out, ref_out)


@pytest.mark.slow  # the default run has the same through the CLI (test_cli.py::test_real_kitti_cli)
def test_real_kitti_two_frames(tmp_path: Path, shared_data: Path, real_labeler: None) -> None:
    """Real data in the default run: 2 KITTI 2015 frames with K=3, full search range 128."""
    out = tmp_path / "kitti"
    summary = run(JobSpec(dataset="kitti15", root=shared_data / "kitti15", out=out, limit=2, shard_size=1, jobs=2,
                          quiet=True, config=LabelerConfig(k=3, max_disp=128)))
    assert summary.pairs_labeled == 2 and verify(out) == []
    m = summary.metrics
    # Loose but meaningful: semi-dense labels that are mostly right (the full quality bars live in A2's
    # test_kitti_quality). First SGM version, K=3, D=128 on these frames: density 13 %, bad-3 1.5 %, AEPE 0.63 px.
    assert 5 < m["density"] < 95, m
    assert m["bad3"] < 5.0 and m["epe"] < 1.5, m
    sample = _all_samples(out)["000000_10"]
    assert sample.gt_noc is not None and sample.label.shape == (375, 1242)
    assert np.isfinite(sample.label_right).mean() > 0.1


@pytest.mark.faults
@pytest.mark.slow
def test_dask_workers_in_another_working_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Relative --root/--out reach Dask workers as absolute paths (workers here start in another directory)."""
    distributed = pytest.importorskip("distributed")
    from pvm_labeler.common import io
    from pvm_labeler.common.datasets import make_layered_scene

    work, elsewhere = tmp_path / "work", tmp_path / "elsewhere"
    for view in ("left", "right"):
        (work / "rig" / view).mkdir(parents=True)
    for i in range(2):
        scene = make_layered_scene(64, 128, seed=i)
        io.write_image(work / "rig" / "left" / f"{i:04d}.png", scene["left"])
        io.write_image(work / "rig" / "right" / f"{i:04d}.png", scene["right"])
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # the workers start here
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        monkeypatch.chdir(work)  # the job runs here, with relative paths
        spec = JobSpec(dataset="folder", root=Path("rig"), out=Path("labels"), config=LabelerConfig(k=2, max_disp=48),
                       shard_size=1, quiet=True, backend="dask", scheduler=cluster.scheduler_address)
        summary = run(spec)
    assert summary.pairs_labeled == 2 and not summary.failures
    assert verify(work / "labels") == [] and read_index(work / "labels").num_samples == 2
    assert not (elsewhere / "labels").exists()


@pytest.mark.parametrize("root_level, expected", [(logging.WARNING, logging.WARNING), (logging.INFO, logging.WARNING),
                                                  (logging.DEBUG, logging.NOTSET)])
def test_dasks_info_lines_only_with_debug_logging(root_level: int, expected: int,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """--backend dask printed ~35 INFO lines of the scheduler and nannies even with --quiet: its loggers are held
    at WARNING unless the run logs at debug level (-vv)."""
    distributed = pytest.importorskip("distributed")
    from pvm_labeler import parallel

    class Refused:  # stands in for the cluster: the loggers are set before it starts
        def __init__(self, *args: object, **kwargs: object) -> None:
            raise OSError("no cluster in this test")

    monkeypatch.setattr(distributed, "LocalCluster", Refused)
    monkeypatch.setattr(logging.getLogger(), "level", root_level)
    monkeypatch.setattr(logging.getLogger("distributed"), "level", logging.NOTSET)
    with pytest.raises(OSError, match="no cluster"):
        list(parallel._run_dask(str, ["a"], 1, None))
    assert logging.getLogger("distributed").level == expected

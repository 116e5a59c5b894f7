"""Spare cores: CoreTokens (flock per core), run_two (second view beside the first), and that neither changes a label.

The job gives its loky / threading workers one CoreTokens; the parent holds the workers' tokens (SpareCores) and
frees those of workers with no shard left; the right view of an SGM pair runs on a helper thread only while a
second core is owned (thread budget >= 2) or borrowed (a free token). These tests pin each branch, including that
a killed holder gives its token back.
"""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from pvm_labeler.config import LabelerConfig
from pvm_labeler.parallel import CoreTokens, SpareCores, run_two, thread_budget
from pvm_labeler.sgm import sgm_pair

BARRIER_S = 20.0  # generous: only a broken run_two (no concurrency) ever waits this long, and then fails


class TestCoreTokens:
    def test_count_and_release(self, tmp_path: Path) -> None:
        tokens = CoreTokens(str(tmp_path), 2)
        a, b = tokens.try_acquire(), tokens.try_acquire()
        assert a is not None and b is not None
        assert tokens.try_acquire() is None  # both cores taken
        CoreTokens.release(a)
        c = tokens.try_acquire()
        assert c is not None and tokens.try_acquire() is None
        CoreTokens.release(b)
        CoreTokens.release(c)

    def test_killed_holder_gives_its_token_back(self, tmp_path: Path) -> None:
        tokens = CoreTokens(str(tmp_path), 1)
        code = ("import time; from pvm_labeler.parallel import CoreTokens; "
                f"fd = CoreTokens({str(tmp_path)!r}, 1).try_acquire(); print('held', fd is not None, flush=True); "
                "time.sleep(600)")
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                                cwd=Path(__file__).resolve().parents[1])
        try:
            assert proc.stdout is not None and proc.stdout.readline().strip() == "held True"
            assert tokens.try_acquire() is None
        finally:
            proc.kill()
            proc.wait()
        fd = tokens.try_acquire()
        assert fd is not None, "the kernel drops a dead process's flock"
        CoreTokens.release(fd)


class TestRunTwo:
    def test_one_core_runs_in_order_on_this_thread(self) -> None:
        log: list[tuple[str, int, bool]] = []
        with thread_budget(1):
            a, b = run_two(lambda: log.append(("first", threading.get_ident(), False)) or 1,
                           lambda concurrent: log.append(("second", threading.get_ident(), concurrent)) or 2)
        me = threading.get_ident()
        assert (a, b) == (1, 2)
        assert log == [("first", me, False), ("second", me, False)]

    def test_two_owned_cores_run_side_by_side(self) -> None:
        barrier, log = threading.Barrier(2, timeout=BARRIER_S), []

        def first() -> str:
            barrier.wait()  # returns only if second runs at the same time
            return "a"

        def second(concurrent: bool) -> str:
            log.append(("second", threading.get_ident(), concurrent))
            barrier.wait()
            return "b"

        with thread_budget(2):
            assert run_two(first, second) == ("a", "b")
        assert log[0][1] != threading.get_ident() and log[0][2] is True

    def test_borrows_a_free_token_only(self, tmp_path: Path) -> None:
        tokens = CoreTokens(str(tmp_path), 2)
        log: list[bool] = []
        with SpareCores(tokens, jobs=2, threads=1) as spare, thread_budget(1, tokens):
            spare.outstanding(2)  # both workers busy: no spare core
            run_two(lambda: None, lambda concurrent: log.append(concurrent))
            assert log == [False]
            spare.outstanding(1)  # the other worker finished: its core is spare now
            barrier = threading.Barrier(2, timeout=BARRIER_S)
            run_two(barrier.wait, lambda concurrent: (log.append(concurrent), barrier.wait()))
            assert log == [False, True]
        assert tokens.try_acquire() is not None  # the helper and SpareCores gave every token back

    def test_helper_exception_is_raised(self) -> None:
        barrier = threading.Barrier(2, timeout=BARRIER_S)

        def second(concurrent: bool) -> None:
            barrier.wait()
            raise ValueError("boom in the helper")

        with thread_budget(2), pytest.raises(ValueError, match="boom in the helper"):
            run_two(barrier.wait, second)


@pytest.mark.parametrize("paths", [8, 4])
def test_sgm_pair_side_by_side_is_bit_identical(paths: int) -> None:
    rng = np.random.default_rng(3)
    # smooth random texture (a plain random field is too noisy for a clean SGM optimum)
    base = cv2.GaussianBlur(rng.integers(0, 256, (48, 180), dtype=np.uint8), (5, 5), 1.0)
    left, right = base[:, 12:172].copy(), base[:, 20:180].copy()  # left(x) = right(x - 8): disparity 8
    cfg = LabelerConfig(max_disp=40, paths=paths)
    with thread_budget(1):
        seq_l, seq_r = sgm_pair(left, right, cfg, uniqueness=True)
    with thread_budget(2):
        par_l, par_r = sgm_pair(left, right, cfg, uniqueness=True)
    assert par_l.uniqueness is not None
    for a, b in ((seq_l, par_l), (seq_r, par_r)):
        for name in ("disp", "conf", "uniqueness"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert np.nanmedian(par_l.disp[:, 48:]) == pytest.approx(8.0, abs=0.25)


class TestSpareCores:
    def test_frees_the_cores_of_idle_workers_only(self, tmp_path: Path) -> None:
        tokens = CoreTokens(str(tmp_path), 4)

        def free() -> int:
            fds = []
            while (fd := tokens.try_acquire()) is not None:
                fds.append(fd)
            for fd in fds:
                CoreTokens.release(fd)
            return len(fds)

        with SpareCores(tokens, jobs=3, threads=1) as spare:
            assert free() == 1  # 4 cores, 3 single-core workers: one core is spare from the start
            spare.outstanding(7)
            assert free() == 1
            spare.outstanding(2)  # 2 shards left for 3 workers
            assert free() == 2
            spare.outstanding(0)
            assert free() == 4
        assert free() == 4

    def test_two_threads_per_worker(self, tmp_path: Path) -> None:
        tokens = CoreTokens(str(tmp_path), 4)
        with SpareCores(tokens, jobs=2, threads=2) as spare:
            assert tokens.try_acquire() is None
            spare.outstanding(1)
            fds = [tokens.try_acquire(), tokens.try_acquire(), tokens.try_acquire()]
            assert fds[0] is not None and fds[1] is not None and fds[2] is None
            for fd in fds[:2]:
                CoreTokens.release(fd)

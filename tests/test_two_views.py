"""The two SGM views side by side: run_two (second view beside the first when the thread owns 2 cores), and that
it never changes a label.

(The job's spare-core lending, CoreTokens / SpareCores, was removed: it bought no clear gain, docs/labeling.md.)
"""

from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest

from pvm_labeler.config import LabelerConfig
from pvm_labeler.parallel import run_two, thread_budget
from pvm_labeler.sgm import sgm_pair

BARRIER_S = 20.0  # generous: only a broken run_two (no concurrency) ever waits this long, and then fails


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

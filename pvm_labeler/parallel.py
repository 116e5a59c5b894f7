"""Fan-out of shard tasks over joblib (loky / threading) or a Dask distributed cluster, with a thread budget.

One task = one shard: the worker that runs it is the only process writing that shard file (h5py: one writer
per file), and results stream back as tasks finish so the caller can update its progress bar and, if killed,
leave only complete shards behind.

Thread budget: ``workers x numba threads <= cores``. Every task calls :func:`thread_budget` around its work, which
sets numba's (and OpenCV's) thread count for the duration and restores the old values afterwards. joblib's loky
backend additionally caps NUMBA_NUM_THREADS / OMP_NUM_THREADS in its workers to cores // n_jobs. A frame's two SGM
views run side by side (:func:`run_two`) when the calling thread's budget is >= 2 cores.

A job whose workers own one core each used to lend an idle worker's core to the frames still running at its end
(``CoreTokens`` / ``SpareCores``); it bought no clear gain in an A/B run and was removed (docs/labeling.md).
"""

from __future__ import annotations

import contextlib
import logging
import os
import resource
import threading
import uuid
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

from pvm_labeler.common.errors import ConfigError

logger = logging.getLogger(__name__)

BACKENDS: tuple[str, ...] = ("loky", "threading", "dask")

T = TypeVar("T")
R = TypeVar("R")
A = TypeVar("A")
B = TypeVar("B")


def available_cores() -> int:
    """CPU cores this process may use (affinity-aware)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def numba_threads_per_worker(jobs: int, cores: int | None = None) -> int:
    """Numba threads each of ``jobs`` workers may use so that jobs x threads <= cores (at least 1)."""
    cores = available_cores() if cores is None else cores
    return max(1, cores // max(1, jobs))


class _Budget(threading.local):
    """The calling thread's cores, as set by :func:`thread_budget`."""

    threads: int | None = None  # None: not set by thread_budget (then numba's thread count decides)


_budget = _Budget()


@contextlib.contextmanager
def thread_budget(threads: int) -> Iterator[None]:
    """Run the body with numba and OpenCV limited to ``threads`` threads, then restore the previous settings."""
    import cv2
    import numba

    threads = max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS))
    old_numba, old_cv, old_budget = numba.get_num_threads(), cv2.getNumThreads(), _budget.threads
    numba.set_num_threads(threads)
    cv2.setNumThreads(threads)
    _budget.threads = threads
    try:
        yield
    finally:
        numba.set_num_threads(old_numba)
        cv2.setNumThreads(old_cv)
        _budget.threads = old_budget


def budget_threads() -> int:
    """Cores the calling thread owns: its :func:`thread_budget`, else numba's thread count (all cores by default)."""
    if _budget.threads is not None:
        return _budget.threads
    import numba

    return int(numba.get_num_threads())


_helpers: ThreadPoolExecutor | None = None
_helpers_lock = threading.Lock()


def _forget_helpers() -> None:
    global _helpers
    _helpers = None  # a forked child has none of its parent's threads; run_two would run ``second`` itself anyway


os.register_at_fork(after_in_child=_forget_helpers)


def _helper_pool() -> ThreadPoolExecutor:
    global _helpers
    with _helpers_lock:
        if _helpers is None:
            _helpers = ThreadPoolExecutor(max_workers=max(2, available_cores()), thread_name_prefix="pvm-helper")
        return _helpers


_NOT_RUN = object()


def _helper(claim: threading.Lock, second: Callable[[bool], B]) -> Any:
    """Run ``second(True)`` if this helper claims it before the calling thread does."""
    return second(True) if claim.acquire(blocking=False) else _NOT_RUN


def run_two(first: Callable[[], A], second: Callable[[bool], B]) -> tuple[A, B]:
    """``first()`` on this thread and ``second`` beside it on a helper thread when this thread owns >= 2 cores.

    The cores are this thread's budget (:func:`budget_threads`). With one core (or if the helper has not started
    ``second`` by the time ``first`` finishes) ``second(False)`` runs here after ``first``. ``second`` receives
    True when it runs concurrently, so it must not share ``first``'s scratch memory then. Both must release the GIL
    to gain anything, and ``second`` must not launch numba ``prange`` kernels (the workqueue threading layer is
    not thread-safe).

    Returns:
        (first's result, second's result); exceptions of either are raised here.
    """
    if budget_threads() < 2:
        result_first = first()
        return result_first, second(False)
    claim = threading.Lock()
    future: Future[Any] = _helper_pool().submit(_helper, claim, second)
    result_first = first()
    if claim.acquire(blocking=False):  # the helper never started it: run it here
        return result_first, second(False)
    return result_first, future.result()


def peak_rss_mb() -> float:
    """Peak resident set size of the calling process, in MiB: VmHWM of /proc/self/status (ru_maxrss without /proc).

    Not ru_maxrss first: Linux keeps it across execve, so a worker spawned (fork + exec) from a big parent reports
    the parent's peak (measured: a spawned child of a 428 MiB process reported 428 MiB; its VmHWM was 28 MiB).
    """
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError, IndexError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def reset_peak_rss() -> bool:
    """Reset this process's peak-RSS mark to its current RSS, so :func:`peak_rss_mb` covers only what follows.

    Linux >= 4.0 (writes "5" to /proc/self/clear_refs; it touches no page). Returns False where that is not
    possible; the peak then covers the process's whole life.
    """
    try:
        with open("/proc/self/clear_refs", "w") as refs:
            refs.write("5")
        return True
    except OSError:
        return False


def run_tasks(
    fn: Callable[[T], R],
    tasks: Iterable[T],
    backend: str = "loky",
    jobs: int = 1,
    scheduler: str | None = None,
) -> Iterator[R]:
    """Apply ``fn`` to every task and yield results in completion order.

    Args:
        fn: a picklable module-level function.
        tasks: picklable task objects.
        backend: "loky" (processes), "threading" or "dask" (dask.distributed; ``scheduler`` address, or a
            LocalCluster with ``jobs`` single-threaded worker processes when None).
        jobs: number of workers (joblib n_jobs; ignored by dask with an explicit scheduler).
        scheduler: Dask scheduler address such as ``tcp://10.0.0.5:8786``.

    Yields:
        ``fn(task)`` results as soon as each finishes.
    """
    tasks = list(tasks)
    if not tasks:
        return
    if backend not in BACKENDS:
        raise ConfigError(f"--backend must be one of {', '.join(BACKENDS)}, got '{backend}'")
    if jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    if backend == "dask":
        yield from _run_dask(fn, tasks, jobs, scheduler)
        return
    if scheduler is not None:
        raise ConfigError(f"--scheduler is only used with --backend dask, got --backend {backend}")
    if jobs == 1:
        # In-process: no pickling, clean tracebacks, and the numba JIT cache of the parent is reused.
        for task in tasks:
            yield fn(task)
        return
    from joblib import Parallel, delayed

    parallel = Parallel(n_jobs=jobs, backend=backend, return_as="generator_unordered", batch_size=1)
    yield from parallel(delayed(fn)(task) for task in tasks)


def _run_dask(fn: Callable[[T], R], tasks: list[T], jobs: int, scheduler: str | None) -> Iterator[R]:
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError as exc:
        raise ConfigError("--backend dask needs dask[distributed]: pip install 'pvstereo[dask]'") from exc
    if logging.getLogger().getEffectiveLevel() > logging.DEBUG:  # dask's INFO lines (~35 a run) only with -vv
        logging.getLogger("distributed").setLevel(logging.WARNING)
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, dashboard_address=None)
        address = cluster.scheduler_address
    else:
        address = scheduler
    try:
        client = Client(address, timeout="30s")
    except OSError as exc:
        if cluster is not None:
            cluster.close()
        raise ConfigError(f"cannot connect to the Dask scheduler at --scheduler {address}: {exc}") from exc
    try:
        logger.info("dask: %d workers at %s", len(client.scheduler_info().get("workers", {})), address)
        # pure=False: every task runs even if two look alike; retries=0: a failure is reported, not hidden.
        run_id = uuid.uuid4().hex[:8]  # unique keys: a shared scheduler may still remember an earlier run's keys
        futures = [client.submit(fn, task, pure=False, key=f"pvm-shard-{run_id}-{i}") for i, task in enumerate(tasks)]
        for future in as_completed(futures):
            yield future.result()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()

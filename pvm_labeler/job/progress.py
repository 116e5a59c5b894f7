"""The job's progress bar (tqdm on stderr), advanced per finished pair where the workers can reach the parent."""

from __future__ import annotations

import queue
import sys
import threading
from typing import Any

from pvm_labeler.job.spec import JobSpec
from pvm_labeler.job.worker import ShardTask


def progress_bar(total: int, initial: int, quiet: bool, desc: str = "pvm-label") -> Any:
    """A tqdm bar over ``total`` pairs, ``initial`` of them done already; off when quiet or stderr is no TTY."""
    from tqdm import tqdm

    disable = quiet or not sys.stderr.isatty()
    return tqdm(total=total, initial=initial, unit="pair", desc=desc, file=sys.stderr, disable=disable,
                dynamic_ncols=True)


class PairProgress:
    """Advance the bar per finished pair: workers put 1 per pair into a queue that a parent thread drains.

    Only when the bar is shown, and not for Dask (remote workers cannot reach a local queue; the bar then
    advances per shard). loky workers get a multiprocessing Manager queue proxy, threads a plain queue.
    """

    def __init__(self, bar: Any, spec: JobSpec, tasks: list[ShardTask]) -> None:
        self.bar, self.spec, self.tasks = bar, spec, tasks
        self.active = not bar.disable and bool(tasks) and spec.backend != "dask"
        self._manager: Any = None
        self._queue: Any = None
        self._thread: threading.Thread | None = None

    def __enter__(self) -> PairProgress:
        if self.active:
            if self.spec.jobs > 1 and self.spec.backend == "loky":
                import multiprocessing

                self._manager = multiprocessing.Manager()
                self._queue = self._manager.Queue()
            else:
                self._queue = queue.SimpleQueue()
            for task in self.tasks:
                task.progress = self._queue
            self._thread = threading.Thread(target=self._drain, name="pvm-label-progress", daemon=True)
            self._thread.start()
        return self

    def _drain(self) -> None:
        while (item := self._queue.get()) is not None:
            self.bar.update(item)

    def __exit__(self, *exc: object) -> None:
        try:
            if self._thread is not None:
                self._queue.put(None)  # FIFO: every worker's put happened before its task returned
                self._thread.join(timeout=30)
        finally:
            if self._manager is not None:
                self._manager.shutdown()
            self.bar.close()

"""How a training run ends early: nothing left to train, or a signal.

* Nothing to do: ``--resume RUN_DIR`` of a run already at its ``--steps`` trains nothing and touches nothing
  (:func:`nothing_to_do`: the summary the loop returns instead of rewriting summary.json and the weights).
* A signal: under :func:`stop_on_signal`, SIGINT (Ctrl-C) or SIGTERM lets the step under way finish, then the run
  saves a checkpoint at that step (atomically, the one ``--resume`` reads) and raises :class:`TrainingInterrupted`
  naming it and the resume command; ``optstereo-train`` exits 128 + the signal's number (130 for Ctrl-C). A second
  signal aborts at once (KeyboardInterrupt) without a checkpoint. Single-process runs only: under DDP the ranks
  would stop at different steps and hang in the next all-reduce, so they keep the default handlers.
"""

from __future__ import annotations

import contextlib
import os
import shlex
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from types import FrameType
from typing import Any

from optstereo import distributed as ddp
from optstereo.checkpoint import LAST
from optstereo.training.checkpoints import TrainState, checkpoint_saver, numbered_checkpoint
from optstereo.training.config import TrainConfig

#: The signals :func:`stop_on_signal` turns into a checkpoint and a clean stop.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class TrainingInterrupted(KeyboardInterrupt):
    """A signal stopped the run after a completed step, whose checkpoint was saved; ``str()`` says where and how
    to resume. ``exit_code`` is the shell's for a death by that signal (130 for SIGINT, 143 for SIGTERM)."""

    def __init__(self, message: str, signum: int, step: int, checkpoint: Path) -> None:
        super().__init__(message)
        self.signum, self.step, self.checkpoint = signum, step, checkpoint
        self.exit_code = 128 + signum


class _StopRequested(Exception):
    """Raised by :meth:`SignalStop.watch` in place of the next batch once a stop signal came."""


def nothing_to_do(run_dir: Path, step: int, steps: int) -> dict[str, Any]:
    """The summary of a resumed run that is already at (or past) its ``steps``: it trains nothing and leaves
    summary.json, config.yaml and the weights as they are. ``"nothing_to_do"`` holds the message to print."""
    where = f"at step {step} of {steps}" if step == steps else f"at step {step}, past --steps {steps}"
    message = f"{run_dir} is already {where}: nothing to do; raise --steps to continue"
    return {"run_dir": str(run_dir), "start_step": step, "step": step, "nothing_to_do": message,
            "checkpoint": str(Path(run_dir) / LAST)}


class SignalStop:
    """The stop request of :func:`stop_on_signal`: its handler records the first signal, and :meth:`watch` hands
    the loop its batches until then."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.pid = os.getpid()

    def handle(self, signum: int, _frame: FrameType | None) -> None:
        """Signal handler: the first signal asks for a stop after the step under way, a second aborts now. A
        DataLoader worker (forked with this handler) ignores it: it keeps serving until the loop stops."""
        if os.getpid() != self.pid:
            return
        if self.signum is not None:
            raise KeyboardInterrupt
        self.signum = signum
        # os.write, not print/logging: a handler may run inside a write to sys.stderr (a reentrant write fails)
        os.write(2, f"\n{signal.Signals(signum).name}: finishing the step under way, then saving a checkpoint "
                    "(send it again to abort without one)\n".encode())

    def watch(self, batches: Iterator[tuple]) -> Iterator[tuple]:
        """``batches``, until a stop signal came: then the next batch is never handed out (the loop stops between
        two steps). A loader error after the signal is the signal's doing (its worker processes got it too)."""
        while self.signum is None:
            try:
                batch = next(batches)
            except StopIteration:
                return
            except Exception as exc:
                if self.signum is None:
                    raise
                raise _StopRequested from exc
            if self.signum is not None:
                break  # came while the batch was loading: its step has not begun
            yield batch
        raise _StopRequested


def ignore_stop_signals(_worker_id: int = 0) -> None:
    """DataLoader ``worker_init_fn``: the data workers ignore SIGINT and SIGTERM, which the training process handles.
    A signal to the whole process group (``timeout``, a session's end, ``kill -- -PGID``) killed the workers first,
    and the run with them, before its checkpoint. The workers still end with the training process (they exit when
    it does: DataLoader's watchdog)."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)


@contextlib.contextmanager
def workers_shut_down(batches: Iterator[Any]) -> Iterator[None]:
    """Around the loop over a DataLoader's iterator ``batches``: its worker processes are shut down when the loop
    ends, however it ends. They ignore the stop signals (:func:`ignore_stop_signals`), so an iterator left to the
    garbage collector kept them alive at exit, where multiprocessing's SIGTERM and join then waited forever."""
    try:
        yield
    finally:
        shutdown = getattr(batches, "_shutdown_workers", None)  # torch's multi-process iterator (none at 0 workers)
        if shutdown is not None:
            shutdown()  # joins each worker, then sends SIGTERM, which they ignore: a wedged one is killed here
            for worker in getattr(batches, "_workers", []):
                if worker.is_alive():
                    worker.kill()
                    worker.join(timeout=5)


@contextlib.contextmanager
def stop_on_signal(state: TrainState, cfg: TrainConfig, info: ddp.DistInfo) -> Iterator[SignalStop]:
    """Around the loop (fed ``stop.watch(batches)``): on SIGINT/SIGTERM the step under way finishes, a checkpoint
    is saved at ``state.step`` (unless the loop just saved that step) and TrainingInterrupted is raised. The
    previous handlers come back on exit. Outside the main thread or under DDP the signals keep their handlers."""
    stop = SignalStop()
    use = info.world_size == 1 and threading.current_thread() is threading.main_thread()
    previous = {signum: signal.signal(signum, stop.handle) for signum in STOP_SIGNALS} if use else {}
    try:
        yield stop
    except _StopRequested:
        assert stop.signum is not None and cfg.out is not None
        run_dir = Path(cfg.out)
        if not numbered_checkpoint(run_dir, state.step).is_file():
            checkpoint_saver(run_dir, cfg, info)(state)
        name = signal.Signals(stop.signum).name
        raise TrainingInterrupted(
            f"{name}: stopped at step {state.step} of {cfg.optim.steps}; checkpoint {run_dir / LAST} (step "
            f"{state.step}); continue with: optstereo-train --resume {shlex.quote(str(run_dir))}",
            stop.signum, state.step, run_dir / LAST) from None
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)

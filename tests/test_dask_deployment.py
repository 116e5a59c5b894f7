"""Labeling on a real Dask deployment that loses a worker: ``dask scheduler`` and two ``dask worker`` processes
(no nanny, so a killed worker stays dead), started as separate processes in another working directory; one worker
gets SIGKILL while it is executing a task; the scheduler hands that task to the other worker, which finishes it
(its story on the scheduler: processing on the victim, then memory from the survivor); the job still finishes, and
its shards equal a ``--jobs 1`` run's.

Loopback addresses only; every wait is bounded.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import make_synthetic_pair

from pvm_labeler.common.io import write_image
from pvm_labeler.shards import open_shard, read_index, read_sample, verify

pytestmark = [pytest.mark.slow, pytest.mark.faults]

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
N_PAIRS = 12
#: Frames big enough (~0.5 s each on one core) that the job is still running when the kill comes.
LABEL_ARGS = ["--dataset", "folder", "--root", "rig", "--k", "2", "--max-disp", "48", "--shard-size", "1", "--quiet"]
BIN = Path(sys.executable).parent


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _start(cmd: list[str], cwd: Path, log: Path) -> subprocess.Popen:
    with log.open("wb") as fh:
        return subprocess.Popen(cmd, cwd=cwd, env=ENV, stdout=fh, stderr=subprocess.STDOUT)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _samples(out: Path) -> dict[str, dict[str, np.ndarray | None]]:
    arrays = {}
    for path, ids in read_index(out).shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                sample = read_sample(h5, frame_id)
                arrays[frame_id] = {k: getattr(sample, k) for k in ("left", "right", "label", "label_right",
                                                                    "confidence")}
    return arrays


@pytest.fixture
def work(tmp_path: Path) -> Path:
    """tmp_path/work/rig: N_PAIRS random-texture pairs, 128x256, disparity 6."""
    rng = np.random.default_rng(3)
    for view in ("left", "right"):
        (tmp_path / "work" / "rig" / view).mkdir(parents=True)
    for i in range(N_PAIRS):
        left, right = make_synthetic_pair(rng, 128, 256, disp=6)
        write_image(tmp_path / "work" / "rig" / "left" / f"{i:03d}.png", left)
        write_image(tmp_path / "work" / "rig" / "right" / f"{i:03d}.png", right)
    return tmp_path / "work"


def test_job_survives_a_killed_dask_worker(work: Path, tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed")
    if shutil.which("dask", path=str(BIN)) is None:
        pytest.skip(f"no dask command beside {sys.executable}")
    # the probes below (_executing, _worker_story) run on the workers, which cannot import this test module
    cloudpickle = pytest.importorskip("cloudpickle")
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    label = [sys.executable, "-m", "pvm_labeler.cli", "run", *LABEL_ARGS]
    reference = subprocess.run([*label, "--out", "ref", "--jobs", "1"], cwd=work, env=ENV, capture_output=True,
                               text=True, timeout=900)
    assert reference.returncode == 0, reference.stderr[-3000:]

    cluster_dir = tmp_path / "cluster"  # scheduler and workers start here, not where the job runs
    cluster_dir.mkdir()
    address = f"tcp://127.0.0.1:{_free_port()}"
    procs: dict[str, subprocess.Popen] = {}
    try:
        procs["scheduler"] = _start([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port",
                                     address.rsplit(":", 1)[1], "--no-dashboard"], cluster_dir,
                                    cluster_dir / "scheduler.log")
        for name in ("w0", "w1"):
            procs[name] = _start([str(BIN / "dask"), "worker", address, "--name", name, "--nthreads", "1",
                                  "--no-nanny", "--no-dashboard", "--host", "127.0.0.1"], cluster_dir,
                                 cluster_dir / f"{name}.log")
        with distributed.Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
            job = subprocess.Popen([*label, "--out", "labels", "--backend", "dask", "--scheduler", address],
                                   cwd=work, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            victim, key = _kill_a_busy_worker(client, procs, work / "labels", job)
            stdout, stderr = job.communicate(timeout=900)
            # the survivor's own log of the task the victim was executing when it died
            stories = client.run(_worker_story, key, on_error="return")
        assert job.returncode == 0, stderr[-3000:]
    finally:
        for proc in procs.values():
            _stop(proc)
    assert procs[victim].returncode == -signal.SIGKILL
    # the victim is dead: only the survivor answers
    (survivor_story,) = [story for story in stories.values() if isinstance(story, list)]
    assert any(event[:3] == (key, "executing", "memory") for event in survivor_story), (key, survivor_story)
    _assert_finished_like_the_reference(work, stdout)


def _worker_story(key: str, dask_worker: object = None) -> list[tuple]:
    """The worker's transitions of ``key`` (run on each worker): ``(key, start, finish, ...)`` tuples."""
    return [tuple(event) for event in dask_worker.state.story(key)]


def _executing(dask_worker: object = None) -> list[str]:
    """Keys the worker is executing right now (run on a worker)."""
    return [str(ts.key) for ts in dask_worker.state.executing]


def _assert_finished_like_the_reference(work: Path, stdout: str) -> None:
    assert f"{N_PAIRS}/{N_PAIRS} pairs" in stdout, stdout
    assert verify(work / "labels") == []
    ref, got = _samples(work / "ref"), _samples(work / "labels")
    assert sorted(got) == sorted(ref) and len(ref) == N_PAIRS
    for frame_id, arrays in ref.items():
        for name, expected in arrays.items():
            np.testing.assert_array_equal(got[frame_id][name], expected, err_msg=f"{frame_id}/{name}")


def _kill_a_busy_worker(client: object, procs: dict[str, subprocess.Popen], out: Path,
                        job: subprocess.Popen) -> tuple[str, str]:
    """Once a shard is done (so both workers have started), SIGKILL a worker that is executing a task (asked of
    the workers themselves, not the scheduler's queue); returns its name and the task's key."""
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline and job.poll() is None:
        if any(out.glob("shard-*.h5")):
            names = {addr: info["name"] for addr, info in client.scheduler_info()["workers"].items()}
            executing = {addr: keys for addr, keys in client.run(_executing).items() if keys and addr in names}
            if executing:
                addr, keys = next(iter(executing.items()))
                procs[names[addr]].send_signal(signal.SIGKILL)
                procs[names[addr]].wait(timeout=60)
                return names[addr], keys[0]
        time.sleep(0.05)
    raise AssertionError(f"the job ended (or timed out) before a worker could be killed: {job.poll()}")

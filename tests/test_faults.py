"""Faults: a training run killed with SIGKILL resumes to bit-identical weights; a kill inside a checkpoint write
leaves the previous checkpoint usable (and its ``*.tmp`` debris is never taken for a checkpoint).

The trainer runs as a subprocess (``python -m optstereo.cli train``, CPU, one torch thread, no DataLoader workers)
so a real SIGKILL hits it at an arbitrary point: inside a step, a checkpoint write or a log write.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import TINY, make_shards, tiny_config

from optstereo.checkpoint import LAST, load_checkpoint, resolve_checkpoint
from optstereo.training import loop
from optstereo.training.checkpoints import config_for_resume

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # the in-process run; the subprocesses get --threads 1

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}
#: Steps of the runs compared; checkpoints every 2 steps, a kill once one past step KILL_AFTER exists.
STEPS = 14


def _train_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "optstereo.cli", "train", *args]


def _new_run(labels: Path, out: Path, workers: int = 0, ckpt_every: int = 2) -> list[str]:
    """A tiny CPU run that uses every random draw the trainer has: shuffling, crop, scale, flip-swap, photometric
    jitter, occluders, the cascade start, L_T's transformations, and the OneCycle LR position."""
    model_opts = [f"--set=model.{k}={v}" for k, v in TINY.items()]
    return _train_cmd(
        "--labels", str(labels), "--out", str(out), "--steps", str(STEPS), "--batch-size", "2", "--crop", "32x128",
        "--iters", "2", "--schedule", "onecycle", "--photometric", "--flip-swap-p", "0.5", "--occlude-p", "0.5",
        "--cascade-p", "0.5", "--lambda-t", "0.1", "--scale-range", "0.95,1.05", "--seed", "7",
        "--workers", str(workers), "--threads", "1", "--device", "cpu", "--log-every", "1",
        "--ckpt-every", str(ckpt_every), "--set", "data.shuffle_buffer=4", "--set", "tensorboard=false", "--quiet",
        *model_opts,
    )


def _checkpoint_steps(run_dir: Path) -> list[int]:
    steps = []
    for path in run_dir.glob("ckpt-*.pt"):
        try:
            steps.append(int(path.stem.split("-")[1]))
        except (IndexError, ValueError):
            continue
    return steps


def _kill_after_checkpoint(cmd: list[str], run_dir: Path, past_step: int, delay_s: float) -> None:
    """Start ``cmd``, SIGKILL it ``delay_s`` after a checkpoint past ``past_step`` appears in ``run_dir``."""
    proc = subprocess.Popen(cmd, cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 600
        while proc.poll() is None and time.monotonic() < deadline:
            if any(s > past_step for s in _checkpoint_steps(run_dir)):
                break
            time.sleep(0.01)
        assert proc.poll() is None, f"the run ended before the kill: {proc.communicate()[1].decode()[-2000:]}"
        time.sleep(delay_s)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
        proc.stdout.close()
        proc.stderr.close()


def _run(cmd: list[str]) -> None:
    result = subprocess.run(cmd, cwd=REPO, env=ENV, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]


@pytest.fixture(scope="module")
def fault_shards(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """6 synthetic 32x144 pairs in 3 shards (more samples than a batch, so epochs and shuffling matter)."""
    return make_shards(tmp_path_factory.mktemp("faults") / "shards", n=6, shard_size=2, height=32, width=144)


@pytest.fixture(scope="module")
def full_run(fault_shards: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The uninterrupted run of STEPS steps every killed run is compared with."""
    out = tmp_path_factory.mktemp("full") / "run"
    _run(_new_run(fault_shards, out))
    return out


@pytest.fixture(scope="module")
def full_run_workers(fault_shards: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same uninterrupted run with two DataLoader worker processes."""
    out = tmp_path_factory.mktemp("full") / "run-workers"
    _run(_new_run(fault_shards, out, workers=2, ckpt_every=3))
    return out


@pytest.mark.slow
@pytest.mark.faults
@pytest.mark.parametrize("kill_after, delay_s", [(2, 0.0), (5, 0.3), (8, 0.05)])
def test_sigkill_then_resume_is_bit_identical(fault_shards: Path, full_run: Path, tmp_path: Path, kill_after: int,
                                              delay_s: float) -> None:
    full, part = full_run, tmp_path / "part"
    _kill_after_checkpoint(_new_run(fault_shards, part), part, kill_after, delay_s)
    killed_at = load_checkpoint(part).step
    # last.pt is copied after ckpt-N.pt is written: a kill between the two leaves last.pt one checkpoint behind
    assert 0 < killed_at < STEPS, f"the kill missed the run (last.pt at step {killed_at})"
    _run(_train_cmd("--resume", str(part), "--quiet"))
    a, b = load_checkpoint(full), load_checkpoint(part)
    assert a.step == b.step == STEPS
    assert a.model_state.keys() == b.model_state.keys()
    differing = [k for k in a.model_state if not torch.equal(a.model_state[k], b.model_state[k])]
    assert not differing, f"resumed from step {killed_at}: {len(differing)} tensors differ, e.g. {differing[:3]}"
    for key in ("exp_avg", "exp_avg_sq"):
        for pid, state in a.optimizer["state"].items():
            assert torch.equal(state[key], b.optimizer["state"][pid][key]), (pid, key)
    assert a.scheduler["last_epoch"] == b.scheduler["last_epoch"] == STEPS
    assert LAST in {p.name for p in part.iterdir()}


@pytest.mark.slow
@pytest.mark.faults
def test_sigkill_then_resume_is_bit_identical_with_loader_workers(fault_shards: Path, full_run_workers: Path,
                                                                  tmp_path: Path) -> None:
    """Two DataLoader workers, resumed at an odd step: the resumed loader asks worker 0 first, so the stream rotates
    the workers' roles to make batch k come from the worker the uninterrupted run took it from."""
    part = tmp_path / "part"
    _kill_after_checkpoint(_new_run(fault_shards, part, workers=2, ckpt_every=3), part, 2, 0.0)
    killed_at = load_checkpoint(part).step
    assert killed_at in (3, 9), f"want a resume at an odd step, got last.pt at step {killed_at}"
    _run(_train_cmd("--resume", str(part), "--quiet"))
    a, b = load_checkpoint(full_run_workers), load_checkpoint(part)
    assert a.step == b.step == STEPS
    differing = [k for k in a.model_state if not torch.equal(a.model_state[k], b.model_state[k])]
    assert not differing, f"resumed from step {killed_at}: {len(differing)} tensors differ, e.g. {differing[:3]}"


#: A child process that rewrites one checkpoint forever: write i holds step i and every weight equal to i.
WRITER = """
import sys
from pathlib import Path
import torch
from optstereo.checkpoint import save_checkpoint
torch.manual_seed(0)
model = torch.nn.Linear(2048, 4096)  # 32 MiB of weights: a write takes long enough to be hit mid-way
target = Path(sys.argv[1])
i = 0
while True:
    i += 1
    with torch.no_grad():
        model.weight.fill_(i)
        model.bias.fill_(-i)
    save_checkpoint(target, model=model, step=i)
    print(i, flush=True)
"""


def _kill_writer(target: Path, delay_s: float) -> int:
    """Run WRITER until its first write is done plus ``delay_s``, SIGKILL it; the last write it reported done."""
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(target)], cwd=REPO, env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()  # blocks until write 1 is renamed into place
        assert first.strip() == "1", proc.stderr.read()[-2000:]
        time.sleep(delay_s)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        done = [int(line) for line in [first, *proc.stdout.read().split()] if line.strip()]
    finally:
        proc.stdout.close()
        proc.stderr.close()
    return done[-1]


@pytest.mark.slow
@pytest.mark.faults
def test_kill_inside_checkpoint_writes_leaves_the_previous_checkpoint(tmp_path: Path) -> None:
    target = tmp_path / "run" / LAST
    debris = 0
    for round_, delay_s in enumerate((0.05, 0.2, 0.45, 0.8, 1.3)):
        last_done = _kill_writer(target, delay_s)
        ckpt = load_checkpoint(target)  # must load: never half a file under the final name
        # The file is the last write reported done, or the one after it (renamed, killed before the print).
        assert ckpt.step in (last_done, last_done + 1), (round_, ckpt.step, last_done)
        assert torch.equal(ckpt.model_state["weight"], torch.full((4096, 2048), float(ckpt.step)))
        assert torch.equal(ckpt.model_state["bias"], torch.full((4096,), -float(ckpt.step)))
        temps = list(target.parent.glob("*.tmp"))
        debris += len(temps)
        for path in temps:  # the next round starts clean, so each round's debris is its own
            path.unlink()
    # The writer spends nearly all its time inside save_checkpoint: some kill must have cut a write.
    assert debris >= 1, "no kill landed inside a write (no temp file left): the test did not test anything"


def test_resume_ignores_and_removes_temp_files_of_a_cut_write(tiny_shards: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    loop.main(tiny_config(tiny_shards, run, steps=1, ckpt_every=1), progress=False)
    whole = (run / LAST).read_bytes()
    # What a kill inside the next checkpoint write leaves: half a file under temp names, newer than the checkpoints.
    temps = [run / f"ckpt-0000002.pt.{'a' * 12}.tmp", run / f"{LAST}.{'b' * 12}.tmp"]
    for path in temps:
        path.write_bytes(whole[: len(whole) // 2])
    assert resolve_checkpoint(run) == run / LAST
    (run / LAST).rename(tmp_path / "saved-last.pt")
    (run / "model.safetensors").unlink()  # the end-of-run export (weights only): newer than the numbered .pt
    assert resolve_checkpoint(run) == run / "ckpt-0000001.pt"  # the newest file is a temp: not a checkpoint
    (tmp_path / "saved-last.pt").rename(run / LAST)
    resumed = loop.main(config_for_resume(run, {"steps": 2}), resume=True, progress=False)
    assert (resumed["start_step"], resumed["step"]) == (1, 2)
    assert not [p for p in temps if p.exists()] and not list(run.glob("*.tmp"))
    assert load_checkpoint(run).step == 2

"""Runs record absolute paths and older runs' relative ones are found
(or named) on resume; a resume with nothing to train touches nothing; a resume that changes settings says which;
Ctrl-C / SIGTERM save a checkpoint at the last completed step and exit 130 / 143; --resume of a run without a
checkpoint says to start again; an --init without a step logs none; model.safetensors gets the umask's mode."""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner
from conftest import TINY, make_shards, tiny_config

from optstereo.checkpoint import export_safetensors, load_checkpoint, save_checkpoint
from optstereo.cli import train_main
from optstereo.models import build_model
from optstereo.training import loop, runpaths
from optstereo.training.checkpoints import config_for_resume, init_weights
from optstereo.training.runpaths import started_from
from optstereo.training.stopping import TrainingInterrupted
from pvm_labeler.common.errors import ConfigError

pytestmark = pytest.mark.usefixtures("one_torch_thread")

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}


def _as_old_run(run: Path, labels: str, out: str) -> None:
    """Make ``run`` look like a run written before paths were recorded absolute: ``data.labels`` and ``out`` as
    typed (relative) in its last.pt and config.yaml."""
    ckpt = load_checkpoint(run)
    config = {**ckpt.train_config, "out": out, "data": {**ckpt.train_config["data"], "labels": labels}}
    model = build_model(ckpt.model_name, **{k: v for k, v in ckpt.model_config.items() if k != "name"})
    model.load_state_dict(ckpt.model_state)
    save_checkpoint(run / "last.pt", model=model, step=ckpt.step, train_config=config)
    (run / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))


@pytest.fixture
def finished_run(tiny_shards: Path, tmp_path: Path) -> Path:
    """A tiny run of 2 steps, finished (model.safetensors, summary.json)."""
    loop.main(tiny_config(tiny_shards, tmp_path / "run", steps=2), progress=False)
    return tmp_path / "run"


class TestPaths:
    def test_new_run_records_absolute_paths_and_resumes_from_elsewhere(
            self, tiny_shards: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        (tmp_path / "a").mkdir()
        shutil.copytree(tiny_shards, tmp_path / "labels")
        monkeypatch.chdir(tmp_path / "a")
        loop.main(tiny_config(Path("../labels"), Path("../run"), steps=2), progress=False)
        saved = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
        assert saved["data"]["labels"] == str(tmp_path / "labels") and saved["out"] == str(tmp_path / "run")
        assert load_checkpoint(tmp_path / "run").train_config["data"]["labels"] == str(tmp_path / "labels")
        monkeypatch.chdir(tmp_path)
        result = CliRunner().invoke(train_main, ["--resume", "run", "--steps", "3", "--quiet"])
        assert result.exit_code == 0, result.output
        assert "trained 2 -> 3 steps" in result.output

    def test_old_relative_paths_are_found_from_where_the_run_started(
            self, finished_run: Path, tiny_shards: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
            caplog: pytest.LogCaptureFixture) -> None:
        shutil.copytree(tiny_shards, tmp_path / "labels")
        (tmp_path / "elsewhere").mkdir()
        _as_old_run(finished_run, labels="labels", out="run")  # started from tmp_path
        monkeypatch.chdir(tmp_path / "elsewhere")
        with caplog.at_level(logging.WARNING):
            cfg = config_for_resume(Path("../run"), {"steps": 3})
        assert cfg.data.labels == tmp_path / "labels" and cfg.out == tmp_path / "run"
        assert "relative to the directory the run was started from" in caplog.text
        assert "changes the run's saved settings" not in caplog.text  # the same labels, found: no change

    def test_old_relative_path_not_found_names_field_file_and_flag(
            self, finished_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        _as_old_run(finished_run, labels="../out/labels", out="somewhere/else")
        monkeypatch.chdir(tmp_path)
        with pytest.raises(ConfigError) as err:
            config_for_resume(Path("run"), {"steps": 3})
        message = str(err.value)
        assert "data.labels ../out/labels" in message and str(Path("run") / "config.yaml") in message
        assert "--labels PATH" in message and "ShardError" not in message
        result = CliRunner().invoke(train_main, ["--resume", "run", "--steps", "3"])
        assert result.exit_code == 2 and "data.labels ../out/labels" in result.output

    def test_relative_path_given_again_resumes(self, finished_run: Path, tiny_shards: Path, tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
        _as_old_run(finished_run, labels="../out/labels", out="somewhere/else")
        monkeypatch.chdir(tmp_path)
        cfg = config_for_resume(Path("run"), {"steps": 3, "labels": tiny_shards})
        assert cfg.data.labels == tiny_shards

    @pytest.mark.parametrize("out, run_dir, path, found", [
        ("run", "/data/run", "labels", "/data/labels"),
        ("out/run2", "/w/out/run2", "../out/labels", "/out/labels"),
        ("../out/run1", "/w/out/run1", "../out/labels", "/w/out/labels"),  # the hidden name does not matter
        ("../out/run1", "/w/out/run1", "labels", None),  # it does: unknown
        ("other/run", "/w/out/run1", "labels", None),
        ("/abs/run", "/w/out/run1", "labels", None),
    ])
    def test_started_from(self, out: str, run_dir: str, path: str, found: str | None) -> None:
        start = started_from(out, Path(run_dir))
        resolved = None if start is None else os.path.normpath(start / path)
        assert (None if resolved is None or runpaths._UNKNOWN in resolved else resolved) == found


class TestNothingToDo:
    def test_resume_of_a_finished_run_touches_nothing(self, finished_run: Path) -> None:
        files = ("summary.json", "model.safetensors", "config.yaml", "last.pt", "metrics.jsonl")
        before = {name: (finished_run / name).read_bytes() for name in files}
        result = CliRunner().invoke(train_main, ["--resume", str(finished_run), "--steps", "2"])
        assert result.exit_code == 0, result.output
        assert f"{finished_run} is already at step 2 of 2: nothing to do; raise --steps to continue" in result.output
        assert "nan" not in result.output and "trained" not in result.output
        assert {name: (finished_run / name).read_bytes() for name in files} == before
        assert json.loads(before["summary.json"])["last"]  # and it still has its last logs

    def test_past_the_steps(self, finished_run: Path) -> None:
        summary = loop.main(config_for_resume(finished_run, {"steps": 1}), resume=True, progress=False)
        assert "at step 2, past --steps 1: nothing to do" in summary["nothing_to_do"]


class TestChangedSettings:
    def test_resume_warns_of_each_changed_setting(self, finished_run: Path,
                                                  caplog: pytest.LogCaptureFixture) -> None:
        with caplog.at_level(logging.WARNING):
            config_for_resume(finished_run, {"lr": 5e-3, "crop": "96x160", "steps": 9, "max_minutes": 1.0})
        warning = next(r.getMessage() for r in caplog.records if "changes the run's saved settings" in r.getMessage())
        assert "optim.lr: 0.0001 -> 0.005" in warning and "data.crop: [32, 64] -> [96, 160]" in warning
        assert "steps" not in warning and "max_minutes" not in warning

    def test_a_finished_run_is_not_said_to_continue(self, finished_run: Path,
                                                     caplog: pytest.LogCaptureFixture) -> None:
        """At its --steps nothing runs, so no "the run continues with the new values" for a changed setting."""
        with caplog.at_level(logging.WARNING):
            config_for_resume(finished_run, {"lr": 5e-3, "steps": 2})
        assert not any("changes the run's saved settings" in r.getMessage() for r in caplog.records)

    def test_steps_alone_warn_nothing(self, finished_run: Path, caplog: pytest.LogCaptureFixture) -> None:
        with caplog.at_level(logging.WARNING):
            config_for_resume(finished_run, {"steps": 9, "max_minutes": 2.0, "threads": 1})
        assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def _interrupt_at(monkeypatch: pytest.MonkeyPatch, step: int, signum: int) -> None:
    """Send ``signum`` to this process in the middle of step ``step`` (after its forward pass), as Ctrl-C would."""
    real = loop.train_step

    def train_step(state, *args, **kwargs):
        if state.step + 1 == step:
            # without the trainer's handler the signal would stop (SIGINT) or kill (SIGTERM) pytest itself
            assert signal.getsignal(signum) not in (signal.SIG_DFL, signal.default_int_handler), "no handler"
            os.kill(os.getpid(), signum)
        return real(state, *args, **kwargs)

    monkeypatch.setattr(loop, "train_step", train_step)


class TestInterrupt:
    @pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
    def test_signal_finishes_the_step_saves_and_resumes_exactly(
            self, tiny_shards: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, signum: int,
            code: int) -> None:
        full = loop.main(tiny_config(tiny_shards, tmp_path / "full", schedule="onecycle"), progress=False)
        _interrupt_at(monkeypatch, 3, signum)
        handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        with pytest.raises(TrainingInterrupted) as err:  # ckpt_every 2: step 3 is saved by the interrupt only
            loop.main(tiny_config(tiny_shards, tmp_path / "part", schedule="onecycle"), progress=False)
        assert {s: signal.getsignal(s) for s in handlers} == handlers  # put back
        assert (err.value.step, err.value.exit_code) == (3, code)
        assert f"--resume {tmp_path / 'part'}" in str(err.value)
        assert load_checkpoint(tmp_path / "part").step == 3 and not list((tmp_path / "part").glob("*.tmp"))
        monkeypatch.undo()
        resumed = loop.main(config_for_resume(tmp_path / "part"), resume=True, progress=False)
        assert (resumed["start_step"], resumed["step"]) == (3, 4)
        assert resumed["param_checksum"] == pytest.approx(full["param_checksum"], rel=1e-6)

    def test_ctrl_c_of_the_cli_saves_a_checkpoint_and_exits_130(self, tiny_shards: Path, tmp_path: Path) -> None:
        """The real thing: SIGINT to a training subprocess once it logged a step."""
        run = tmp_path / "run"
        proc, stderr = _signal_after_first_step(tiny_shards, run, "0", lambda p: p.send_signal(signal.SIGINT))
        assert proc.returncode == 130, stderr[-3000:]
        step = load_checkpoint(run).step
        logged = [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()]
        assert step >= 1 and logged[-1] == step  # the last completed step, every one of them logged
        assert f"SIGINT: stopped at step {step} of 100000" in stderr
        assert f"continue with: optstereo-train --resume {run}" in stderr and "Aborted!" not in stderr
        more = CliRunner().invoke(train_main, ["--resume", str(run), "--steps", str(step + 1), "--quiet"])
        assert more.exit_code == 0, more.output
        assert f"trained {step} -> {step + 1} steps" in more.output

    def test_sigterm_to_the_process_group_saves_a_checkpoint(self, tiny_shards: Path, tmp_path: Path) -> None:
        """SIGTERM to the whole process group (``timeout``, a session's end): with a data worker, the worker used to
        die first and take the run with it ('DataLoader worker ... is killed by signal: Terminated', no checkpoint);
        now the worker ignores it and the run saves, exiting 143."""
        run = tmp_path / "run"
        proc, stderr = _signal_after_first_step(tiny_shards, run, "1", lambda p: os.killpg(p.pid, signal.SIGTERM))
        assert proc.returncode == 143, stderr[-3000:]
        step = load_checkpoint(run).step
        assert step >= 1 and f"SIGTERM: stopped at step {step} of 100000" in stderr and "killed by signal" not in stderr

    def test_resume_without_a_checkpoint_says_to_start_again(self, tiny_shards: Path, tmp_path: Path) -> None:
        run = tmp_path / "run"
        run.mkdir()
        tiny_config(tiny_shards, run).save(run)  # what a run killed before its first checkpoint leaves
        result = CliRunner().invoke(train_main, ["--resume", str(run)])
        assert result.exit_code == 1
        assert "the run never saved one" in result.output and f"--config {run / 'config.yaml'}" in result.output


    def test_resume_of_a_labels_folder_names_it(self, tiny_shards: Path) -> None:
        """--resume given the shards' folder (its config.yaml is the labeler's): exit 2 saying what it is, not the
        "never saved a checkpoint, start again with --config ..." advice that then failed on the labeler's keys."""
        result = CliRunner().invoke(train_main, ["--resume", str(tiny_shards), "--steps", "5"])
        assert result.exit_code == 2, result.output
        assert "is a folder of shards (pvm-label's), not a training run: give it to --labels" in " ".join(
            result.output.split())
        from optstereo.training.checkpoints import _resume_source

        (tiny_shards / "last.pt").write_bytes(b"")  # a run whose --out was its --labels: it resumes
        try:
            assert _resume_source(tiny_shards) == tiny_shards
        finally:
            (tiny_shards / "last.pt").unlink()

    def test_ctrl_c_outside_the_steps_exits_130_saying_what_is_left(self, tiny_shards: Path, tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
        """Ctrl-C while the start is scored (before the steps' handler) or at the end: exit 130 naming the
        checkpoint to resume, or that none was written, not click's bare "Aborted!" with exit 1."""
        def interrupted(*_: object, **__: object) -> None:
            raise KeyboardInterrupt

        monkeypatch.setattr("optstereo.cli.train.main", interrupted)
        run = tmp_path / "run"
        args = ["--labels", str(tiny_shards), "--out", str(run), "--steps", "2", "--workers", "0",
                *(f"--set=model.{k}={v}" for k, v in TINY.items())]
        first = CliRunner().invoke(train_main, args)
        assert first.exit_code == 130 and "Aborted!" not in first.output, first.output
        assert f"interrupted before the first checkpoint: none in {run}" in first.output
        monkeypatch.undo()
        loop.main(tiny_config(tiny_shards, run, steps=2), progress=False)
        monkeypatch.setattr("optstereo.cli.train.main", interrupted)
        later = CliRunner().invoke(train_main, ["--resume", str(run), "--steps", "4"])
        assert later.exit_code == 130 and f"the last checkpoint is {run / 'last.pt'} (step 2)" in later.output, \
            later.output
        assert f"continue with: optstereo-train --resume {run}" in later.output


def _signal_after_first_step(labels: Path, run: Path, workers: str,
                             send: Callable[[subprocess.Popen], None]) -> tuple[subprocess.Popen, str]:
    """Start `optstereo-train` (tiny model, endless steps, ``workers`` data workers) in a process group of its own,
    ``send`` it a signal once it logged a step; (the finished process, its stderr)."""
    cmd = [sys.executable, "-m", "optstereo.cli", "train", "--labels", str(labels), "--out", str(run),
           "--steps", "100000", "--batch-size", "2", "--crop", "32x64", "--iters", "2", "--workers", workers,
           "--threads", "1", "--device", "cpu", "--log-every", "1", "--ckpt-every", "100000",
           "--set", "tensorboard=false", *(f"--set=model.{k}={v}" for k, v in TINY.items())]
    proc = subprocess.Popen(cmd, cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # its own process group, as a shell job's
    try:
        deadline = time.monotonic() + 300
        while proc.poll() is None and time.monotonic() < deadline:
            if (run / "metrics.jsonl").is_file() and (run / "metrics.jsonl").read_text().strip():
                break
            time.sleep(0.05)
        assert proc.poll() is None, f"the run ended before the signal: {proc.communicate()[1][-2000:]}"
        send(proc)
        _, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    return proc, stderr


class TestNits:
    def test_init_without_a_step_logs_none(self, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
        model = build_model("optstereo", **TINY)
        export_safetensors(tmp_path / "w.safetensors", model)  # no step: stored as -1
        with caplog.at_level(logging.INFO, logger="optstereo.training.checkpoints"):
            init_weights(build_model("optstereo", **TINY), tmp_path / "w.safetensors")
        assert [r.getMessage() for r in caplog.records] == [f"initialised from {tmp_path / 'w.safetensors'}"]
        caplog.clear()
        export_safetensors(tmp_path / "s.safetensors", model, step=7)
        with caplog.at_level(logging.INFO, logger="optstereo.training.checkpoints"):
            init_weights(build_model("optstereo", **TINY), tmp_path / "s.safetensors")
        assert "(its step 7)" in caplog.text

    def test_safetensors_export_gets_the_umask_mode(self, tmp_path: Path) -> None:
        old = os.umask(0o022)
        try:
            path = export_safetensors(tmp_path / "m.safetensors", build_model("optstereo", **TINY))
            plain = tmp_path / "plain"
            plain.write_text("x")
        finally:
            os.umask(old)
        assert path.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777 == 0o644
        assert load_checkpoint(path).step == -1 and not list(tmp_path.glob("*.tmp"))


def test_under_torchrun_only_rank_0_prints_the_summary(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every rank runs the command; the run's closing lines come once, from rank 0."""
    from click.testing import CliRunner

    import optstereo.cli.train as train_cli
    from optstereo.cli import train_main

    summary = {"start_step": 0, "step": 4, "seconds": 1.0, "last": {"L_P": 0.5}, "checkpoint": "RUN/last.pt"}
    monkeypatch.setattr(train_cli, "main", lambda *a, **k: summary)
    shards = make_shards(tmp_path / "s", n=1, shard_size=1)
    args = ["--labels", str(shards), "--out", str(tmp_path / "run"), "--quiet"]
    assert "trained 0 -> 4 steps" in CliRunner(env={"RANK": "0"}).invoke(train_main, args).output
    other = CliRunner(env={"RANK": "1"}).invoke(train_main, args)
    assert other.exit_code == 0 and "trained" not in other.output, other.output


def test_a_resumed_runs_tensorboard_curves_hold_each_step_once(tmp_path: Path) -> None:
    """A run killed at step 5 after its checkpoint at 3, resumed: TensorBoard's reader shows steps 1..6 once each
    (it showed 1, 2, 3, 4, 5, 4, 5, 6: the killed run's events past the checkpoint stayed), as metrics.jsonl does."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # lazy: optional package

    from optstereo.training.log import RunLogger  # lazy: only this test logs by hand

    first = RunLogger(tmp_path, enabled=True, tensorboard=True)
    for step in range(1, 6):
        first.scalars(step, {"loss": float(step)})
    first.close()
    resumed = RunLogger(tmp_path, enabled=True, tensorboard=True, resume_step=3)
    for step in range(4, 7):
        resumed.scalars(step, {"loss": 10.0 + step})
    resumed.close()
    events = EventAccumulator(str(tmp_path / "tb"))
    events.Reload()
    tag = next(t for t in events.Tags()["scalars"] if t.endswith("loss"))
    seen = [(e.step, e.value) for e in events.Scalars(tag)]
    assert seen == [(1, 1.0), (2, 2.0), (3, 3.0), (4, 14.0), (5, 15.0), (6, 16.0)]
    assert [json.loads(line)["step"] for line in (tmp_path / "metrics.jsonl").read_text().splitlines()] == \
        [1, 2, 3, 4, 5, 6]


def test_resume_with_another_out_is_refused(tmp_path: Path) -> None:
    """--resume RUN --out OTHER used to continue RUN in place without a word (OTHER never made, RUN's checkpoints
    rotated): a usage error naming both and the --init way to branch a run; nothing is written."""
    run = tmp_path / "run"
    run.mkdir()
    result = CliRunner().invoke(train_main, ["--resume", str(run), "--out", str(tmp_path / "other"), "--steps", "9"])
    assert result.exit_code == 2, result.output
    assert f"--resume {run} continues that run in its own folder" in result.output
    assert f"--init {run / 'last.pt'} --out {tmp_path / 'other'}" in result.output
    assert not (tmp_path / "other").exists() and list(run.iterdir()) == []


def test_a_continued_run_drops_its_earlier_finish(finished_run: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A finished run (step 2) continued to 4 and stopped midway: its summary.json and model.safetensors of step 2
    used to stay beside last.pt of a later step and pass for the run's result; they go when it continues."""
    assert (finished_run / "summary.json").is_file() and (finished_run / "model.safetensors").is_file()

    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("stopped midway")

    monkeypatch.setattr(loop, "train_steps", broken)
    with pytest.raises(RuntimeError, match="stopped midway"):
        loop.main(config_for_resume(finished_run, {"steps": 4}), resume=True, progress=False)
    assert not (finished_run / "summary.json").exists() and not (finished_run / "model.safetensors").exists()
    assert load_checkpoint(finished_run).step == 2  # the weights are still there


def _wedged(ready: object) -> None:
    """A data worker stuck in I/O that ignores SIGTERM, as the training's workers do."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    ready.set()  # type: ignore[attr-defined]
    time.sleep(600)


def test_a_wedged_worker_is_killed_when_the_loop_ends() -> None:
    """torch's shutdown ends with SIGTERM, which the workers ignore (ignore_stop_signals): a worker still alive after
    it is killed, so the trainer can exit (multiprocessing's exit would join it forever)."""
    import multiprocessing

    from optstereo.training.stopping import workers_shut_down

    context = multiprocessing.get_context("fork")
    ready = context.Event()
    worker = context.Process(target=_wedged, args=(ready,), daemon=True)
    worker.start()
    assert ready.wait(timeout=30)
    batches = type("Batches", (), {"_shutdown_workers": lambda self: worker.terminate(), "_workers": [worker]})()
    try:
        with workers_shut_down(batches):
            pass
        worker.join(timeout=10)
        assert not worker.is_alive() and worker.exitcode == -signal.SIGKILL
    finally:  # a regression fails here instead of hanging pytest's exit on the worker
        if worker.is_alive():
            worker.kill()


def test_metrics_jsonl_is_strict_json(tmp_path: Path) -> None:
    """A non-finite value (a diverged loss) is written as null, as summary.json writes it: the file held a bare NaN,
    which strict JSON readers (jq, JavaScript, pandas' engine) refuse."""
    from optstereo.training.log import RunLogger  # lazy: only these tests log by hand

    run_logger = RunLogger(tmp_path, enabled=True, tensorboard=False)
    run_logger.scalars(1, {"total": float("nan"), "L_P": float("inf"), "L_R": 0.5})

    def refuse(constant: str) -> None:
        raise ValueError(f"not JSON: {constant}")

    record = json.loads((tmp_path / "metrics.jsonl").read_text(), parse_constant=refuse)
    assert record == {"step": 1, "total": None, "L_P": None, "L_R": 0.5}

"""optstereo-adapt into an OUT that already holds an adaptation, and its user-facing output: a re-run with other
options is refused before anything is done (the same options resume), split.json is never redrawn under a started
run, the final files are whole or absent, the decision's numbers are readable, GT bars only with GT, and the
labeler's failures come out once with what to do. The pipeline's heavy steps are stand-ins here (labels are
synthetic shards, training writes a file, scoring returns fixed scores); test_adapt.py runs the real ones."""

from __future__ import annotations

import errno
import json
import shutil
import signal
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import make_synthetic_pair

import optstereo.cli.adapt as adapt_cli
from optstereo import adapt, adapt_record
from optstereo.adapt import AdaptConfig
from optstereo.adapt_label import MEND_HINT, LabelingError, _Relay, label_rig
from optstereo.adapt_report import change_text, report_markdown, score_text
from optstereo.cli import adapt_main
from optstereo.training.stopping import TrainingInterrupted
from optstereo.validation import PairScore
from pvm_labeler.common.datasets import make_layered_scene
from pvm_labeler.common.errors import ConfigError
from pvm_labeler.common.io import write_image
from pvm_labeler.shards import ShardRecord, write_shard_dir

FRAMES = 6


def _labels(out: Path, gt: bool = False) -> Path:
    """FRAMES synthetic frames as a labeling job's shards (GT on the first two with ``gt``)."""
    rng = np.random.default_rng(0)
    records = []
    for i in range(FRAMES):
        left, right = make_synthetic_pair(rng, 16, 32, 2)
        label = np.full((16, 32), 2.0, np.float32)
        label[:, :8] = np.nan
        records.append(ShardRecord(f"f{i}", left, right, label, label.copy(), np.isfinite(label).astype(np.float32),
                                   gt=np.full((16, 32), 2.0, np.float32) if gt and i < 2 else None))
    return write_shard_dir(out, records, config={"k": 1}, shard_size=2)


@pytest.fixture
def fake(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """adapt.run with stand-ins for labeling, training and scoring; records what ran."""
    calls: dict[str, Any] = {"label": 0, "train": []}

    def label(dataset, root, out, *args, **kwargs):
        calls["label"] += 1
        return out if (out / "index.json").is_file() else _labels(out)

    def finetune(cfg, labels):
        run_dir = cfg.out / "run"
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "last.pt").write_bytes(b"trained weights")
        calls["train"].append((cfg.steps, cfg.learning_rate()))
        return run_dir / "last.pt", cfg.steps or 7

    def score(checkpoint, labels, ids, device="auto", quiet=False, what=""):
        better = 0.1 if what == "after" else 0.0  # the adapted weights: PVM EPE lower on every frame
        return [PairScore(i, pvm_n=100, pvm_err=100 * (1.0 - better + k / 100), photo_sum=10.0, photo_n=100)
                for k, i in enumerate(ids)]

    monkeypatch.setattr(adapt, "label_rig", label)
    monkeypatch.setattr(adapt, "finetune", finetune)
    monkeypatch.setattr(adapt, "score_frames", score)
    start = tmp_path / "start.safetensors"
    start.write_bytes(b"start weights")
    calls["cfg"] = AdaptConfig(dataset="folder", root=tmp_path, out=tmp_path / "out", init=str(start), steps=2,
                               device="cpu", quiet=True)
    return calls


def _args(cfg: AdaptConfig, *more: str) -> list[str]:
    return ["--root", str(cfg.root), "--out", str(cfg.out), "--init", str(cfg.init), "--quiet", *more]


def test_a_rerun_with_other_options_is_refused_before_anything(fake: dict[str, Any]) -> None:
    cfg: AdaptConfig = fake["cfg"]
    first = adapt.run(cfg)
    assert first["adapted"] and fake["train"] == [(2, 1e-5)] and (cfg.out / adapt_record.RECORD).is_file()
    before = {p.name: p.read_bytes() for p in cfg.out.iterdir() if p.is_file()}
    res = CliRunner().invoke(adapt_main, _args(cfg, "--steps", "12", "--lr", "1e-4", "--seed", "1"))
    assert res.exit_code == 2, res.output
    for words in ("--steps 2 -> 12", "--lr 1e-05 -> 0.0001", "--seed 0 -> 1", "fresh --out"):
        assert words in res.output
    assert fake["label"] == 1 and len(fake["train"]) == 1  # nothing was done
    assert {p.name: p.read_bytes() for p in cfg.out.iterdir() if p.is_file()} == before  # split.json as it was
    with pytest.raises(ConfigError, match="--holdout 0.3 -> 0.5"):
        adapt.run(AdaptConfig(**{**vars(cfg), "holdout": 0.5}))
    # the same options on a finished adaptation: nothing to do (it scored and copied everything again), its answer
    res = CliRunner().invoke(adapt_main, _args(cfg, "--steps", "2", "--device", "cpu", "--threads", "1"))
    assert res.exit_code == 0, res.output
    assert f"{first['decision']}; checkpoint {first['checkpoint']}" in res.output
    assert fake["label"] == 1 and len(fake["train"]) == 1
    # an unfinished one (no report.json) resumes, whatever the device, the output's noise or the threads
    (cfg.out / adapt_record.REPORT).unlink()
    res = CliRunner().invoke(adapt_main, _args(cfg, "--steps", "2", "--device", "cpu", "--threads", "1"))
    assert res.exit_code == 0, res.output
    assert fake["label"] == 2 and fake["train"][-1] == (2, 1e-5)
    assert json.loads((cfg.out / "split.json").read_text()) == json.loads(before["split.json"])


def test_a_folder_typed_another_way_is_the_same_option(fake: dict[str, Any]) -> None:
    """`--left cam0/` then `--left ./cam0` (or a record of an older optstereo-adapt holding `cam0/`): the same folder,
    so the re-run resumes; it was refused as "--left cam0/ -> ./cam0". Another folder is still refused."""
    cfg: AdaptConfig = AdaptConfig(**{**vars(fake["cfg"]), "reader_options": {"left": "cam0/", "right": "cam1"}})
    adapt.run(cfg)
    record = cfg.out / adapt_record.RECORD
    assert json.loads(record.read_text())["left"] == "cam0"
    (cfg.out / adapt_record.REPORT).unlink()  # unfinished: a re-run resumes it
    adapt.run(AdaptConfig(**{**vars(cfg), "reader_options": {"left": "./cam0", "right": "cam1/"}}))
    older = {**json.loads(record.read_text()), "left": "cam0/"}  # as an older version recorded it
    record.write_text(json.dumps(older))
    (cfg.out / adapt_record.REPORT).unlink()
    adapt.run(AdaptConfig(**{**vars(cfg), "reader_options": {"left": "cam0", "right": "cam1"}}))
    assert len(fake["train"]) == 3
    with pytest.raises(ConfigError, match="left cam0 -> cam2"):
        adapt.run(AdaptConfig(**{**vars(cfg), "reader_options": {"left": "cam2", "right": "cam1"}}))


def test_split_json_is_never_redrawn_under_a_started_run(tmp_path: Path) -> None:
    out = tmp_path / "out"
    adapt_record.write_split(out, ["a", "b"], ["c"])
    adapt_record.write_split(out, ["a", "c"], ["b"])  # nothing trained yet: a new draw may replace it
    (out / "run").mkdir()
    with pytest.raises(ConfigError, match="trained on other frames"):
        adapt_record.write_split(out, ["a", "b"], ["c"])
    assert json.loads((out / "split.json").read_text()) == {"train": ["a", "c"], "held_back": ["b"]}


def test_a_failed_copy_leaves_no_adapted_file_and_no_report(fake: dict[str, Any],
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    cfg: AdaptConfig = fake["cfg"]
    adapt.run(cfg)
    assert (cfg.out / "report.json").is_file() and (cfg.out / "adapted.pt").is_file()
    (cfg.out / "report.json").unlink()  # killed before its report: the re-run decides again, over the old adapted.pt

    def disk_full(src: Path, dst: Path) -> None:
        Path(dst).write_bytes(Path(src).read_bytes()[:3])
        raise OSError(errno.ENOSPC, "No space left on device")

    real_copy = shutil.copyfile
    monkeypatch.setattr(adapt_record.shutil, "copyfile", disk_full)
    with pytest.raises(OSError, match="No space left"):
        adapt.run(cfg)
    assert sorted(p.name for p in cfg.out.glob("adapted*")) == []  # no half file under any name
    assert not (cfg.out / "report.json").exists()  # the earlier report no longer marks it finished
    monkeypatch.setattr(adapt_record.shutil, "copyfile", real_copy)
    report = adapt.run(cfg)
    assert (cfg.out / "adapted.pt").read_bytes() == b"trained weights"
    assert json.loads((cfg.out / "report.json").read_text())["decision"] == report["decision"]
    assert (cfg.out / "report.md").stat().st_mtime_ns <= (cfg.out / "report.json").stat().st_mtime_ns


def test_the_decisions_numbers_have_the_digits_they_need() -> None:
    assert change_text("pvm_epe", -0.00087, 0.0012) == "pvm_epe -0.0009 (noise 0.0012)"
    assert change_text("pvm_epe", -0.25, 0.1) == "pvm_epe -0.250 (noise 0.100)"
    assert change_text("photometric", -0.00019, 0.00011) == "photometric -0.00019 (noise 0.00011)"
    assert change_text("photometric", -1e-9, 0.004) == "photometric 0.0000 (noise 0.0040)"  # not "-0.0000"
    assert change_text("photometric", 0.0, 0.0) == "photometric unchanged"
    assert score_text("photometric", 0.021346) == "0.02135" and score_text("pvm_epe", 1.23456) == "1.235"
    before = [PairScore(str(i), pvm_n=1000, pvm_err=e, photo_sum=20.0, photo_n=1000) for i, e in
              enumerate([500.0, 600.0, 400.0])]
    after = [PairScore(s.frame_id, pvm_n=1000, pvm_err=s.pvm_err - d, photo_sum=20.0, photo_n=1000)
             for s, d in zip(before, [1.0, 1.1, 0.9], strict=True)]
    reason = adapt.decide(before, after).reason
    assert "pvm_epe -0.00100 (noise 0.00012)" in reason and "photometric unchanged" in reason
    assert "held-back frame," in adapt.decide(before[:1], after[:1]).reason  # 1 held-back frame


def test_the_report_says_one_step_and_one_minute() -> None:
    base = {"pairs": 1, "held_back_frames": [], "init": "v15", "before": {}, "after": {}, "decision": "d",
            "checkpoint": "a", "lr": 1e-5}
    words = report_markdown({**base, "steps": 1, "config": {"steps": None, "minutes": 1.0, "teacher": None}})
    assert "1 pair (0 held back)" in words and "1 step (as many as fit 1 minute) at lr 1e-05." in words


def test_gt_is_scored_and_shown_only_on_frames_with_gt(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    plain = _labels(tmp_path / "plain")
    assert adapt.gt_frames(plain) == []
    monkeypatch.setattr(adapt, "load_model", lambda *a, **k: pytest.fail("no GT: no model, no progress bar"))
    assert adapt.gt_scores("start", plain, [], quiet=False) == {}
    assert adapt.gt_frames(_labels(tmp_path / "gt", gt=True)) == ["f0", "f1"]


def test_the_relay_holds_the_labelers_error_and_passes_the_rest(capsys: pytest.CaptureFixture[str]) -> None:
    relay = _Relay()
    for piece in ("label:  50%\r", "label: 100%\n", "ERROR worker: pair 2 failed\n", "Err", "or: no stereo ",
                  "pairs found\n  in x\n"):
        relay.feed(piece)
    assert relay.finish() == "no stereo pairs found\n  in x"
    assert capsys.readouterr().err == "label:  50%\rlabel: 100%\nERROR worker: pair 2 failed\n"


def _rig(root: Path, n: int = 4) -> None:
    for i in range(n):
        scene = make_layered_scene(48, 96, seed=i)
        for side in ("left", "right"):
            (root / side).mkdir(parents=True, exist_ok=True)
            write_image(root / side / f"{i:03d}.png", scene[side])


def test_a_labeling_failure_is_one_error_and_leaves_no_out(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    out = tmp_path / "out"
    res = CliRunner().invoke(adapt_main, ["--root", str(tmp_path / "empty"), "--out", str(out), "--quiet"])
    assert res.exit_code == 1, res.output
    assert res.output.count("Error") == 1 and "RuntimeError" not in res.output and "neither a directory" in res.output
    assert not out.exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    res = CliRunner().invoke(adapt_main, ["--root", str(tmp_path / "empty"), "--out", str(kept), "--quiet"])
    assert res.exit_code == 1 and kept.is_dir() and list(kept.iterdir()) == []  # not ours to remove


def test_a_corrupt_image_says_what_to_do(tmp_path: Path) -> None:
    _rig(tmp_path / "rig")
    bad = tmp_path / "rig" / "left" / "002.png"
    data = cv2.imencode(".png", cv2.imread(str(bad)))[1].tobytes()
    bad.write_bytes(data[: len(data) // 2])  # a valid header, truncated data: the labeler labels the others
    with pytest.raises(LabelingError) as err:
        label_rig("folder", tmp_path / "rig", tmp_path / "labels", {}, max_disp=32, quiet=True)
    assert "002" in str(err.value) and "failures.json" in str(err.value) and MEND_HINT in str(err.value)
    bad.write_bytes(b"not a png")  # an unreadable header: the labeler refuses them all, naming the pair
    with pytest.raises(LabelingError, match="unusable") as err:
        label_rig("folder", tmp_path / "rig", tmp_path / "labels2", {}, max_disp=32, quiet=True)
    assert MEND_HINT in str(err.value) and "skip-unusable" not in str(err.value)  # pvm-label's flag, not adapt's


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupted_adaptation_says_how_to_continue(signum: int, code: int, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C in adaptation's training: the checkpoint is saved; the CLI exits as the signal would and says to run the
    same command again (it used to print click's "Aborted!", exit 1, no hint; the trainer's own text names
    optstereo-train --resume, which is not how an adaptation continues)."""
    def interrupted(cfg: object) -> None:
        raise TrainingInterrupted("SIGINT: ... continue with: optstereo-train --resume X", signum, 7, tmp_path / "c")

    monkeypatch.setattr(adapt_cli, "run", interrupted)
    (tmp_path / "l").mkdir()
    result = CliRunner().invoke(adapt_cli.adapt_main, ["--root", str(tmp_path), "--left", "l", "--right", "l", "--out",
                                                       str(tmp_path / "o")])
    assert result.exit_code == code
    assert f"{signal.Signals(signum).name}: stopped at step 7, its checkpoint saved" in result.output
    assert "same optstereo-adapt command again" in result.output
    assert "Aborted!" not in result.output and "optstereo-train --resume" not in result.output


def test_the_report_records_the_rate_and_budget_the_run_used(tmp_path: Path) -> None:
    """report.json's config said "lr": null and "minutes": 10.0 for a run given --steps 15 at the default rate:
    it records the rate trained at, and no minutes when the steps were given."""
    cfg = AdaptConfig(dataset="folder", root=tmp_path, out=tmp_path / "o", steps=15)
    config = adapt_record.report_config(cfg)
    assert config["lr"] == cfg.learning_rate() == adapt.DEFAULT_LR and config["minutes"] is None
    assert config["steps"] == 15 and config["root"] == str(tmp_path) and config["out"] == str(tmp_path / "o")
    teacher = adapt_record.report_config(AdaptConfig(dataset="folder", root=tmp_path, out=tmp_path, teacher="t"))
    assert teacher["lr"] == adapt.DEFAULT_TEACHER_LR and teacher["minutes"] == adapt.DEFAULT_MINUTES
    assert json.loads(json.dumps(config)) == config  # JSON-ready


@pytest.mark.parametrize("seconds, words", [(52.0, "budget: 10 steps in 0.5 minutes at 5.20 s per step (the timing "
                                                    "steps alone: over 0.5)"),
                                             (2.0, "budget: 150 steps in 0.5 minutes at 0.20 s per step")])
def test_the_budget_line_says_when_the_timing_steps_alone_overran(seconds: float, words: str, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch,
                                                                 caplog: pytest.LogCaptureFixture) -> None:
    """It said "10 steps fit 0.5 minutes at 5.20 s per step" (52 s)."""
    def timed(cfg, labels, run_dir, steps):
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "summary.json").write_text(json.dumps({"seconds": seconds, "step": 10, "start_step": 0}))
        return run_dir / "last.pt"

    monkeypatch.setattr(adapt, "train_to", timed)
    cfg = AdaptConfig(dataset="folder", root=tmp_path, out=tmp_path / "out", minutes=0.5, quiet=True)
    (tmp_path / "out").mkdir()
    with caplog.at_level("INFO"):
        adapt.budget_steps(cfg, tmp_path, tmp_path / "out" / "run")
    assert words in caplog.text

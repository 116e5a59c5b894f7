"""optstereo.adapt: the held-back frames, the decision by hand, a learning rate that wrecks the weights (the start
is kept), and the whole command end to end on a tiny folder with a tiny model."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY

from optstereo.adapt import MIN_HELD, AdaptConfig, decide, split_frames
from optstereo.checkpoint import model_inference, save_checkpoint
from optstereo.inference import int8
from optstereo.models import build_model
from optstereo.validation import PairScore
from pvm_labeler.common.datasets import discover, load_pair, make_layered_scene
from pvm_labeler.common.io import write_image, write_pfm

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_split_frames_holds_back_whole_frames() -> None:
    ids = [f"{i:03d}" for i in range(10)]
    train, held = split_frames(ids, 0.3, seed=0)
    assert len(held) == 3 and sorted(train + held) == ids and not set(train) & set(held)
    assert split_frames(ids, 0.3, seed=0) == (train, held) and split_frames(ids, 0.3, seed=1) != (train, held)
    assert len(split_frames(ids, 0.5, 0)[1]) == 5
    assert [len(x) for x in split_frames(ids[:4], 0.3, 0)] == [1, MIN_HELD]  # at least MIN_HELD, one to train
    assert split_frames(ids[:3], 0.3, 0) == (ids[:3], [])  # too small: nothing held back, no decision
    assert [len(x) for x in split_frames(ids[:6], 0.99, 0)] == [1, 5]  # a large --holdout keeps one to train on


def _scores(err: list[int], photo: list[float]) -> list[PairScore]:
    """Frames whose PVM EPE is err / 1000 px over 1000 labelled pixels (err = summed error in px)."""
    return [PairScore(str(i), pvm_n=1000, pvm_err=float(e), photo_sum=p * 100, photo_n=100)
            for i, (e, p) in enumerate(zip(err, photo, strict=True))]


def test_decide_by_hand() -> None:
    before = _scores([500, 600, 400, 550], [0.20, 0.30, 0.25, 0.22])
    better = decide(before, _scores([400, 490, 310, 440], [0.20, 0.30, 0.25, 0.22]))  # EPE -0.1/-0.11/-0.09/-0.11
    assert better.adapted and "pvm_epe better beyond noise" in better.reason
    mean, margin = better.changes["pvm_epe"]
    assert mean == pytest.approx(-0.1025)
    assert margin == pytest.approx(2 * np.std([-0.1, -0.11, -0.09, -0.11], ddof=1) / 2)
    noisy = decide(before, _scores([400, 700, 300, 600], [0.20, 0.30, 0.25, 0.22]))  # -0.1, +0.1, -0.1, +0.05
    assert not noisy.adapted and "no held-back score better beyond its noise" in noisy.reason
    mixed = decide(before, _scores([400, 490, 310, 440], [0.30, 0.40, 0.36, 0.31]))  # labels better, photo worse
    assert not mixed.adapted and "worse beyond noise in photometric" in mixed.reason
    few = decide(before[:2], _scores([0, 0], [0.0, 0.0]))
    assert not few.adapted and few.reason.startswith("no decision can be made: 2 held-back frames")
    with pytest.raises(ValueError, match="--holdout"):
        AdaptConfig(dataset="folder", root=None, out=Path("x"), holdout=1.0).check()


def test_a_wrecking_learning_rate_keeps_the_start(tmp_path: Path, shared_data: Path) -> None:
    """Five KITTI 2015 frames at half size as a rig, the shipped default as the start, 3 steps at lr 0.05: the
    adapted weights are ruined, the held-back frames say so, the start is kept (the GT is read after, and agrees)."""
    from optstereo.cli import adapt_main

    rig = tmp_path / "rig"
    for ref in discover("kitti15", shared_data / "kitti15")[:5]:
        pair = load_pair(ref)
        for side, image in (("l", pair.left), ("r", pair.right)):
            (rig / side).mkdir(parents=True, exist_ok=True)
            write_image(rig / side / f"{ref.frame_id}.png", cv2.resize(image, None, fx=0.5, fy=0.5,
                                                                       interpolation=cv2.INTER_AREA))
    out = tmp_path / "adapt"
    res = CliRunner().invoke(adapt_main, ["--root", str(rig), "--left", "l", "--right", "r", "--out", str(out),
                                          "--steps", "3", "--lr", "0.05", "--max-disp", "96", "--device", "cpu",
                                          "--quiet", "--holdout", "0.6"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    report = json.loads((out / "report.json").read_text())
    assert len(report["held_back_frames"]) == 3 and len(report["train_frames"]) == 2
    assert not report["adapted"] and report["decision"].startswith("start kept: held-back frames worse")
    assert report["after"]["held_bad3"] > report["before"]["held_bad3"] + 5
    assert res.output.strip().splitlines()[-1].startswith("start kept:")
    assert (out / "adapted.safetensors").read_bytes() == Path(report["init"]).read_bytes()
    assert Path(report["trained"]).is_file() and report["trained"] in (out / "report.md").read_text()
    clips = int8.read_sidecar(out / "adapted.safetensors")
    assert (clips is not None) is int8.available() and (report["int8_clips"] is not None) is int8.available()
    if clips is not None:
        assert clips == int8.read_sidecar(Path(report["init"]))


def _rig(root: Path, n: int = 2) -> None:
    for i in range(n):
        scene = make_layered_scene(96, 160, seed=i)
        for side, image in (("cam0", scene["left"]), ("cam1", scene["right"])):
            (root / side).mkdir(parents=True, exist_ok=True)
            write_image(root / side / f"{i:03d}.png", image)
        (root / "gt").mkdir(exist_ok=True)
        write_pfm(root / "gt" / f"{i:03d}.pfm", np.nan_to_num(scene["gt"], nan=np.inf))


@pytest.mark.slow
def test_adapt_end_to_end(tmp_path: Path) -> None:
    from optstereo import adapt
    from optstereo.cli import adapt_main

    _rig(tmp_path / "rig", n=4)
    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", model=build_model("optstereo", **TINY), step=0)
    out = tmp_path / "adapt"
    args = ["--root", str(tmp_path / "rig"), "--left", "cam0", "--right", "cam1", "--gt", "gt", "--out", str(out),
            "--init", str(ckpt), "--steps", "3", "--device", "cpu", "--quiet", "--max-disp", "64"]
    res = CliRunner().invoke(adapt_main, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    report = json.loads((out / "report.json").read_text())
    assert report["pairs"] == 4 and report["config"]["steps"] == 3
    held, train = report["held_back_frames"], report["train_frames"]
    assert len(held) == MIN_HELD and len(train) == 1
    for side in ("before", "after"):
        assert report[side]["held_pixels"] > 0 and np.isfinite(report[side]["held_epe"])
        assert math.isfinite(report[side]["photometric_holes"])
        assert "gt_bad3" in report[side]  # the folder has GT: scored after the decision, never trained on
    assert Path(report["checkpoint"]).is_file() and (out / "report.md").is_file()
    assert (out / "run" / "last.pt").is_file() and json.loads((out / "split.json").read_text())["held_back"] == held
    # the training shards hold the training frame only, without GT
    from pvm_labeler.shards import open_shard, read_index, read_sample

    index = read_index(out / "train_labels")
    assert [i for _, ids in index.shards for i in ids] == train
    for path, ids in index.shards:
        with open_shard(path) as h5:
            assert all(read_sample(h5, i).gt is None for i in ids)
    # a second call resumes: labels and training are done, the report is written again
    res = CliRunner().invoke(adapt_main, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    # the default budget instead of --steps: a real timed probe, then as many steps as fit (a tiny model: many more)
    budget_args = [a for a in args if a not in ("--steps", "3")] + ["--minutes", "0.05"]
    budget_args[budget_args.index("--out") + 1] = str(tmp_path / "budget")
    res = CliRunner().invoke(adapt_main, budget_args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    budget = json.loads((tmp_path / "budget/budget.json").read_text())
    report = json.loads((tmp_path / "budget/report.json").read_text())
    assert report["config"]["steps"] is None and report["steps"] == budget["steps"]
    assert budget["steps"] == min(adapt.MAX_STEPS, max(adapt.PROBE_STEPS, int(3.0 / budget["s_per_step"])))
    assert json.loads((tmp_path / "budget/run/summary.json").read_text())["step"] == budget["steps"]


def _holey_shards(out: Path) -> Path:
    """Two synthetic frames whose PVM labels cover only the right half (the table-top case: few labelled pixels)."""
    from conftest import make_synthetic_pair

    from pvm_labeler.shards import ShardRecord, write_shard_dir

    rng = np.random.default_rng(0)
    records = []
    for i in range(2):
        left, right = make_synthetic_pair(rng, 32, 64, 4)
        label = np.full((32, 64), 4.0 + i / 100, np.float32)
        label[:, :32] = np.nan
        conf = np.isfinite(label).astype(np.float32)
        records.append(ShardRecord(f"frame-{i}", left, right, label, label.copy(), conf))
    return write_shard_dir(out, records, config={"k": 1}, shard_size=1)


def test_teacher_fills_only_the_training_frames_holes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from optstereo import adapt
    from optstereo.training.distill import FILL_CONFIDENCE, map_path
    from optstereo.validation import shard_samples

    # a teacher that says 3 px everywhere, in both views: a left pixel x >= 3 finds its match in the right view,
    # the first 3 columns look off the image (inconsistent); so the holes (x < 32) are filled at 3..31, empty at 0..2
    calls = []

    def teacher_views(model, left, right, device="cpu", amp="none"):
        calls.append(left.shape)
        return np.full(left.shape[:2], 3.0, np.float32), np.full(left.shape[:2], 3.0, np.float32)

    monkeypatch.setattr(adapt.distill, "teacher_views", teacher_views)
    train = _holey_shards(tmp_path / "train")
    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", model=build_model("optstereo", **TINY), step=0)
    cfg = AdaptConfig(dataset="folder", root=None, out=tmp_path / "out", teacher=str(ckpt), device="cpu", quiet=True)
    filled = adapt.distill_train_labels(cfg, train)
    originals = {s.frame_id: s for s in shard_samples(train)}
    assert sorted(p.stem for p in (cfg.out / "teacher_maps").glob("*.npz")) == sorted(originals) and len(calls) == 2
    # the teacher is recorded as optstereo-distill maps records it (a fresh run said "no teacher.json ... unrecorded")
    assert json.loads((cfg.out / "teacher_maps" / "teacher.json").read_text())["spec"] == str(ckpt)
    assert json.loads((filled / "index.json").read_text())["distill"]["teacher"]["spec"] == str(ckpt)
    for s in shard_samples(filled):
        o = originals[s.frame_id]
        assert map_path(cfg.out / "teacher_maps", s.frame_id).is_file()
        np.testing.assert_array_equal(s.label[:, 32:], o.label[:, 32:])  # PVM's labels never change
        np.testing.assert_array_equal(s.label[:, 3:32], 3.0)
        assert np.isnan(s.label[:, :3]).all()
        np.testing.assert_allclose(s.confidence[:, 3:32].astype(np.float32), FILL_CONFIDENCE, atol=1e-3)
        np.testing.assert_array_equal(s.confidence[:, 32:].astype(np.float32), 1.0)
    adapt.distill_train_labels(cfg, train)  # a second call finds every map: the teacher is not run again
    assert len(calls) == 2


def test_a_teacher_run_trains_with_confidence_weights(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from optstereo import adapt

    seen = {}
    monkeypatch.setattr(adapt, "main", lambda cfg, **kw: seen.setdefault("cfg", cfg))
    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", model=build_model("optstereo", **TINY), step=0)
    # (teacher, --lr, confidence weights, the rate trained with): 1e-4 with a teacher by default (A1), 1e-5 without
    for teacher, lr, weighted, rate in ((None, None, False, 1e-5), (str(ckpt), None, True, 1e-4),
                                        (str(ckpt), 3e-5, True, 3e-5), (None, 2e-4, False, 2e-4)):
        seen.clear()
        cfg = AdaptConfig(dataset="folder", root=None, out=tmp_path / f"out{weighted}{lr}", init=str(ckpt),
                          teacher=teacher, lr=lr, steps=5, device="cpu", quiet=True)
        adapt.finetune(cfg, tmp_path / "labels")
        assert seen["cfg"].loss.conf_weight is weighted
        assert seen["cfg"].optim.lr == pytest.approx(rate)
    with pytest.raises(ValueError, match="--lr must be > 0"):
        AdaptConfig(dataset="folder", root=None, out=tmp_path, lr=0.0).check()


def test_the_report_names_the_teacher() -> None:
    from optstereo.adapt import report_markdown

    base = {"pairs": 5, "held_back_frames": ["a", "b", "c"], "init": "v15.safetensors", "before": {}, "after": {},
            "decision": "start kept", "checkpoint": "adapted.safetensors"}
    plain = report_markdown({**base, "config": {"steps": 150, "teacher": None}})
    taught = report_markdown({**base, "config": {"steps": 150, "teacher": "pretrained-accurate"}})
    assert "150 steps." in plain and "teacher" not in plain
    assert "150 steps; the teacher `pretrained-accurate` in PVM's holes." in taught
    rated = report_markdown({**base, "lr": 1e-4, "config": {"steps": 150, "teacher": "pretrained-accurate"}})
    assert "150 steps at lr 0.0001; the teacher" in rated
    assert "not chosen" not in plain  # a report without the run's trained weights (older runs) names none
    kept = report_markdown({**base, "adapted": False, "trained": "run/model.safetensors", "config": {"steps": 1}})
    assert "the trained weights, not chosen (use them at your own risk): `run/model.safetensors`" in kept
    assert "not chosen" not in report_markdown({**base, "adapted": True, "trained": "run/model.safetensors",
                                                "config": {"steps": 1}})
    # a --minutes budget: the steps that fit, or what the timing steps alone took when they overran it
    timed = {**base, "steps": 10, "config": {"steps": None, "minutes": 1}}
    assert "10 steps (as many as fit 1 minute)" in report_markdown(
        {**timed, "budget": {"steps": 10, "s_per_step": 3.0}})
    assert "10 steps (the timing steps alone: 2.6 minutes, over 1 minute)" in report_markdown(
        {**timed, "budget": {"steps": 10, "s_per_step": 15.33}})


def test_a_teacher_typo_is_named_before_anything_is_done(tmp_path: Path) -> None:
    """--teacher pretrained-acurate: exit 2 naming --teacher, nothing written (it was found after labelling, and the
    options it left refused the corrected command)."""
    from optstereo.cli import adapt_main

    out = tmp_path / "adapt"
    res = CliRunner().invoke(adapt_main, ["--root", str(tmp_path), "--out", str(out), "--teacher",
                                          "pretrained-acurate", "--quiet"])
    assert res.exit_code == 2 and "--teacher pretrained-acurate:" in res.output, res.output
    assert not out.exists()
    alone = CliRunner().invoke(adapt_main, ["--root", str(tmp_path), "--out", str(out), "--teacher-only"])
    assert alone.exit_code == 2 and "--teacher-only needs --teacher" in alone.output
    assert "ValueError" not in alone.output and not out.exists()  # a usage error, said as one


def test_teacher_only_replaces_the_labels_and_drops_the_photometric_losses(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from optstereo import adapt
    from optstereo.validation import shard_samples

    # the same 3 px teacher as above: consistent at x >= 3 in the left view; PVM's labels (x >= 32) are dropped
    def teacher_views(model, left, right, device="cpu", amp="none"):
        return np.full(left.shape[:2], 3.0, np.float32), np.full(left.shape[:2], 3.0, np.float32)

    monkeypatch.setattr(adapt.distill, "teacher_views", teacher_views)
    train = _holey_shards(tmp_path / "train")
    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", model=build_model("optstereo", **TINY), step=0)
    cfg = AdaptConfig(dataset="folder", root=None, out=tmp_path / "out", init=str(ckpt), teacher=str(ckpt),
                      teacher_only=True, steps=5, device="cpu", quiet=True)
    taught = adapt.distill_train_labels(cfg, train)
    assert taught.name == "train_teacher"
    for s in shard_samples(taught):
        np.testing.assert_array_equal(s.label[:, 3:], 3.0)  # PVM's 4.0x labels gone, the teacher everywhere
        assert np.isnan(s.label[:, :3]).all()
        np.testing.assert_array_equal(s.confidence.astype(np.float32), np.isfinite(s.label).astype(np.float32))
    seen = {}
    monkeypatch.setattr(adapt, "main", lambda c, **kw: seen.setdefault("cfg", c))
    adapt.finetune(cfg, taught)
    assert seen["cfg"].loss.lambda_r == 0.0 and seen["cfg"].loss.lambda_s == 0.0 and seen["cfg"].loss.conf_weight
    with pytest.raises(ValueError, match="--teacher-only needs --teacher"):
        AdaptConfig(dataset="folder", root=None, out=tmp_path, teacher_only=True).check()
    words = adapt.report_markdown({"pairs": 5, "held_back_frames": [], "init": "v15", "before": {}, "after": {},
                                   "decision": "start kept", "checkpoint": "a",
                                   "config": {"steps": 9, "teacher": "t", "teacher_only": True}})
    assert "the teacher `t`'s consistent views alone" in words


def test_a_time_budget_sets_the_steps_from_a_timed_probe(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """No --steps: the first PROBE_STEPS steps are trained and timed, the count fits --minutes (within
    [PROBE_STEPS, MAX_STEPS]), is recorded in OUT/budget.json and reused on resume; --steps skips the probe."""
    from optstereo import adapt

    trained: list[int] = []

    def fake_train_to(cfg: AdaptConfig, labels: Path, run_dir: Path, steps: int) -> Path:
        trained.append(steps)
        run_dir.mkdir(parents=True, exist_ok=True)
        # the probe: 10 steps in 25 s -> 2.5 s per step
        (run_dir / "summary.json").write_text(json.dumps({"seconds": 25.0, "step": steps, "start_step": 0}))
        return run_dir / "last.pt"

    monkeypatch.setattr(adapt, "train_to", fake_train_to)
    cfg = AdaptConfig(dataset="folder", root=None, out=tmp_path / "out", minutes=3.0)
    assert adapt.finetune(cfg, tmp_path / "labels") == (tmp_path / "out/run/last.pt", 72)  # 180 s / 2.5 s
    assert trained == [adapt.PROBE_STEPS, 72]
    assert json.loads((tmp_path / "out/budget.json").read_text())["s_per_step"] == pytest.approx(2.5)
    trained.clear()
    assert adapt.finetune(cfg, tmp_path / "labels")[1] == 72 and trained == [72]  # resumed: no second probe
    for minutes, expected in ((0.01, adapt.PROBE_STEPS), (1e4, adapt.MAX_STEPS)):
        out = tmp_path / f"out{minutes}"
        assert adapt.finetune(AdaptConfig(dataset="folder", root=None, out=out, minutes=minutes),
                              tmp_path / "labels")[1] == expected
    trained.clear()
    fixed = AdaptConfig(dataset="folder", root=None, out=tmp_path / "fixed", steps=7)
    assert adapt.finetune(fixed, tmp_path / "labels")[1] == 7 and trained == [7]
    assert not (tmp_path / "fixed/budget.json").exists()
    with pytest.raises(ValueError, match="--minutes must be > 0"):
        AdaptConfig(dataset="folder", root=None, out=tmp_path, minutes=0.0).check()
    words = adapt.report_markdown({"pairs": 5, "held_back_frames": [], "init": "v15", "before": {}, "after": {},
                                   "decision": "start kept", "checkpoint": "a", "steps": 72,
                                   "config": {"steps": None, "minutes": 3.0, "teacher": None}})
    assert "72 steps (as many as fit 3 minutes)." in words


def test_training_frames_are_resized_to_the_starts_inference_scale(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """at_inference_scale (--inference-scale): a frame the start runs at 2x is trained 2x (images, both views' labels
    times 2 in size and value, confidences in size only); one run at scale 1 stays as it is; all at 1, or the
    default (off): no copy."""
    from optstereo import adapt
    from optstereo.validation import shard_samples

    train = _holey_shards(tmp_path / "train")
    cfg = AdaptConfig(dataset="folder", root=None, out=tmp_path / "out", inference_scale=True, quiet=True)
    monkeypatch.setattr(adapt, "inference_scales", lambda c, labels: {"frame-0": 1.0, "frame-1": 2.0})
    scaled = adapt.at_inference_scale(cfg, train)
    assert scaled == tmp_path / "out/train_scaled"
    before = {s.frame_id: s for s in shard_samples(train)}
    after = {s.frame_id: s for s in shard_samples(scaled)}
    np.testing.assert_array_equal(after["frame-0"].left, before["frame-0"].left)
    np.testing.assert_array_equal(after["frame-0"].label, before["frame-0"].label)
    big = after["frame-1"]
    assert big.left.shape == (64, 128, 3) and big.label.shape == big.label_right.shape == (64, 128)
    np.testing.assert_allclose(big.label[:, 64:], 2 * (4.0 + 1 / 100), rtol=1e-6)  # 4.01 px -> 8.02 px
    assert np.isnan(big.label[:, :64]).all() and np.isnan(big.label_right[:, :64]).all()
    np.testing.assert_array_equal(big.confidence.astype(np.float32), np.isfinite(big.label).astype(np.float32))
    assert big.attrs["train_scale"] == 2.0
    monkeypatch.setattr(adapt, "inference_scales", lambda c, labels: {"frame-0": 1.0, "frame-1": 1.0})
    assert adapt.at_inference_scale(cfg, train) == train
    monkeypatch.setattr(adapt, "inference_scales", lambda c, labels: {"frame-0": 1.0, "frame-1": 2.0})
    assert adapt.at_inference_scale(dataclasses.replace(cfg, inference_scale=False), train) == train


def test_inference_scales_are_the_starts_final_pass_and_cached(tmp_path: Path) -> None:
    """inference_scales: each training frame's final-pass scale as engine.run gives it (a file at input scale 1.5,
    no adaptive pass: 1.5), written to OUT/train_scales.json and read back on resume."""
    from optstereo import adapt

    train = _holey_shards(tmp_path / "train")
    torch.manual_seed(0)
    model = build_model("optstereo", **TINY)
    model.inference_config = model_inference(model).replace(scale=1.5, adaptive_ref_disp=0.0, adaptive_ref_pixels=0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", model=model, step=0)
    cfg = AdaptConfig(dataset="folder", root=None, out=tmp_path / "out", init=str(ckpt), device="cpu", quiet=True)
    cfg.out.mkdir()
    assert adapt.inference_scales(cfg, train) == {"frame-0": 1.5, "frame-1": 1.5}
    (cfg.out / "train_scales.json").write_text(json.dumps({"frame-0": 1.0, "frame-1": 3.0}))
    assert adapt.inference_scales(cfg, train) == {"frame-0": 1.0, "frame-1": 3.0}

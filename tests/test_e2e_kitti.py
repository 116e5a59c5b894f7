"""End to end on real KITTI 2015 frames: pvm-label -> optstereo-train -> resume -> optstereo-eval.

Two frames of ../shared/data are labelled by the real labeler (small K and search range so it takes seconds),
a tiny OptStereo trains a few steps from the shards on small crops, overfits one crop (the loss must fall),
resumes at the saved step, and both the network and the labels are measured on the frames' GT by one ruler.
The full-size version (real model, more steps, all frames) is marked slow.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from optstereo.cli import eval_main, train_main
from optstereo.data.stream import ShardStream
from optstereo.data.transforms import TrainTransform, collate_min_size
from optstereo.training import loop
from optstereo.training.config import TrainConfig
from pvm_labeler.shards import read_index, verify

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY_OPTS = ["--set", "model.feature_dim=16", "--set", "model.hidden_dim=16", "--set", "model.head_dim=16",
             "--set", "model.upsample_dim=8"]


@pytest.fixture(scope="module")
def kitti_shards(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from pvm_labeler.cli import main as pvm_label

    out = tmp_path_factory.mktemp("e2e") / "labels"
    threads = torch.get_num_threads()
    res = CliRunner().invoke(pvm_label, ["run", "--dataset", "kitti15", "--root", str(shared_data / "kitti15"),
                                         "--out", str(out), "--k", "2", "--max-disp", "96", "--limit", "2",
                                         "--shard-size", "1", "--quiet"])
    # The labeler's numba thread budget also resets the OpenMP pool that torch uses; put torch's count back.
    torch.set_num_threads(threads)
    assert res.exit_code == 0, res.output
    assert verify(out) == []
    assert read_index(out).num_samples == 2
    return out


def test_train_resume_eval(kitti_shards: Path, shared_data: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    run = tmp_path / "run"
    args = ["--labels", str(kitti_shards), "--out", str(run), "--steps", "3", "--crop", "64x128", "--iters", "2",
            "--batch-size", "2", "--workers", "1", "--ckpt-every", "3", "--log-every", "1", "--quiet", *TINY_OPTS]
    res = runner.invoke(train_main, args)
    assert res.exit_code == 0, res.output
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2, 3]
    assert all(np.isfinite(r["total"]) and np.isfinite(r["label_epe"]) for r in records)
    assert (run / "last.pt").is_file() and (run / "ckpt-0000003.pt").is_file()

    res = runner.invoke(train_main, ["--resume", str(run), "--steps", "5", "--quiet"])
    assert res.exit_code == 0, res.output
    assert "trained 3 -> 5 steps" in res.output
    steps = [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4, 5]

    res = runner.invoke(eval_main, ["--checkpoint", str(run), "--dataset", "kitti15", "--root",
                                    str(shared_data / "kitti15"), "--limit", "2", "--out", str(tmp_path / "eval"),
                                    "--no-save-maps"])
    assert res.exit_code == 0, res.output
    net = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert net["n_frames"] == 2 and net["density"] == 100.0 and np.isfinite(net["epe"]) and net["d1_noc"] >= 0

    res = runner.invoke(eval_main, ["--labels", str(kitti_shards), "--out", str(tmp_path / "labels")])
    assert res.exit_code == 0, res.output
    labels = json.loads((tmp_path / "labels" / "summary.json").read_text())
    # PVM labels are semi-dense and, where present, far more accurate than an untrained network.
    assert labels["n_frames"] == 2 and 5.0 < labels["density"] < 100.0 and labels["bad3"] < net["bad3"]


def test_overfit_one_crop(kitti_shards: Path, tmp_path: Path) -> None:
    """The loss falls when the trainer sees the same real crop again and again."""
    cfg = TrainConfig.from_dict(dict(
        labels=kitti_shards, out=tmp_path, crop=(64, 128), iters=2, lr=1e-3, batch_size=1, flip_swap_p=0.0,
        model_overrides={"feature_dim": 16, "hidden_dim": 16, "head_dim": 16, "upsample_dim": 8}))
    stream = ShardStream(kitti_shards, transform=TrainTransform(crop=cfg.data.crop, flip_swap_p=0.0), seed=1)
    batch = collate_min_size([next(iter(stream))])
    assert batch[3].float().mean() > 0.05  # the crop carries PVM labels
    torch.manual_seed(0)
    model = loop.build_model(cfg)
    optimizer, scheduler = loop.build_optimizer(model, cfg)
    state = loop.TrainState(model, optimizer, scheduler, torch.amp.GradScaler("cpu", enabled=False))
    loss_fn = loop.build_loss(cfg)
    losses = [loop.train_step(state, batch, loss_fn, cfg, torch.device("cpu"))["L_P"] for _ in range(25)]
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:3]), losses


@pytest.mark.slow
def test_full_model_short_run(kitti_shards: Path, shared_data: Path, tmp_path: Path) -> None:
    """The paper-size model (C = 256) for 10 steps at 320x736 on the labelled frames, then eval on them."""
    run = tmp_path / "run"
    res = CliRunner().invoke(train_main, ["--labels", str(kitti_shards), "--out", str(run), "--steps", "10",
                                          "--batch-size", "1", "--workers", "1", "--quiet"])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(eval_main, ["--checkpoint", str(run / "model.safetensors"), "--dataset", "kitti15",
                                         "--root", str(shared_data / "kitti15"), "--limit", "2",
                                         "--out", str(tmp_path / "eval")])
    assert res.exit_code == 0, res.output

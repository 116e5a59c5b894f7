"""GT shards without a labeling pass: pvm-label pack-gt (= run --labels none) and training on them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from optstereo.data.stream import ShardStream
from pvm_labeler.cli import main as pvm_main
from pvm_labeler.common import io
from pvm_labeler.shards import open_shard, read_index, read_sample


def test_pack_gt_writes_images_and_gt_and_no_labels(tmp_path: Path) -> None:
    out = tmp_path / "gt"
    result = CliRunner().invoke(pvm_main, ["pack-gt", "--dataset", "sample", "--out", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    index = read_index(out)
    assert index.config["extra"] == {"labels": "none"} and index.num_samples == 4
    path, ids = index.shards[0]
    with open_shard(path) as h5:
        sample = read_sample(h5, ids[0])
    assert sample.gt is not None and np.isfinite(sample.gt).any()
    assert not np.isfinite(sample.label).any() and not np.isfinite(sample.label_right).any()
    assert (sample.confidence == 0).all()
    stream = ShardStream(out, supervision="gt", infinite=False, with_ids=True)
    left, right, label, valid, frame_id = next(iter(stream))
    assert valid.any() and label.shape[1:] == left.shape[1:]  # the GT reaches the trainer


def test_pack_gt_needs_gt_for_every_pair_and_writes_nothing_otherwise(tmp_path: Path) -> None:
    rig = tmp_path / "rig"
    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        for side in ("left", "right"):
            io.write_image(rig / side / f"{name}.png", rng.integers(0, 255, (48, 96, 3), dtype=np.uint8))
    out = tmp_path / "gt"
    result = CliRunner().invoke(pvm_main, ["pack-gt", "--dataset", "folder", "--root", str(rig), "--out", str(out),
                                           "--quiet"])
    assert result.exit_code != 0 and "2 of 2 pairs have none" in result.output and "a (" in result.output
    assert not out.exists() or not any(out.iterdir())


def test_a_gt_pack_is_never_resumed_as_labels(tmp_path: Path) -> None:
    out = tmp_path / "d"
    runner = CliRunner()
    args = ["--dataset", "sample", "--out", str(out), "--quiet", "--limit", "1", "--k", "2"]
    assert runner.invoke(pvm_main, ["pack-gt", *args]).exit_code == 0
    again = runner.invoke(pvm_main, ["run", *args])  # a PVM run into the GT pack's directory
    assert again.exit_code != 0 and "labels" in again.output


def test_pack_gt_of_pairs_narrower_than_the_search_range(tmp_path: Path) -> None:
    """A GT pack runs no matcher: pairs narrower than the labeler's 192-px search are packed (the labeling job
    refuses them, since its pyramid could not search them)."""
    from conftest import make_folder

    root = make_folder(tmp_path / "pairs", n=2, size=(32, 64))
    result = CliRunner().invoke(pvm_main, ["pack-gt", "--dataset", "folder", "--root", str(root), "--out",
                                           str(tmp_path / "gt"), "--quiet"])
    assert result.exit_code == 0, result.output
    assert read_index(tmp_path / "gt").num_samples == 2
    labelled = CliRunner().invoke(pvm_main, ["run", "--dataset", "folder", "--root", str(root), "--out",
                                             str(tmp_path / "labels"), "--quiet"])
    assert labelled.exit_code != 0 and "must be smaller than the image width 64" in labelled.output


def test_the_labelers_options_change_nothing_in_a_pack(tmp_path: Path) -> None:
    """pack-gt takes the labeler's options "as they change nothing", yet `pack-gt --k 3 --kappa1 1` made a folder
    that the same pack without them refused ("different config ... config.k: 3 -> 6")."""
    out = tmp_path / "gt"
    first = CliRunner().invoke(pvm_main, ["pack-gt", "--dataset", "sample", "--k", "3", "--kappa1", "1", "--out",
                                          str(out), "--limit", "2", "--quiet"])
    assert first.exit_code == 0, first.output
    again = CliRunner().invoke(pvm_main, ["run", "--labels", "none", "--dataset", "sample", "--out", str(out),
                                          "--limit", "2"])
    assert again.exit_code == 0 and "nothing to do" in again.output, again.output
    assert read_index(out).config["k"] == 6 and read_index(out).config["extra"] == {"labels": "none"}


def test_training_a_gt_pack_on_pvm_labels_is_refused(tmp_path: Path) -> None:
    """A GT pack given to `optstereo-train --labels` without `--supervision gt` trained on nothing but the
    photometric terms (L_P 0.000, exit 0): it is now a usage error naming the pack and the option, before any run
    folder is made."""
    from optstereo.cli import train_main

    out = tmp_path / "gt"
    assert CliRunner().invoke(pvm_main, ["pack-gt", "--dataset", "sample", "--out", str(out), "--quiet"]).exit_code == 0
    run = tmp_path / "run"
    result = CliRunner().invoke(train_main, ["--labels", str(out), "--out", str(run), "--steps", "1", "--workers", "0"])
    assert result.exit_code == 2, result.output
    assert f"{out} is a GT pack" in " ".join(result.output.split()) and "--supervision gt" in result.output
    assert not run.exists()
    index = json.loads((out / "index.json").read_text())  # a pack made before the summary said gt_only
    del index["summary"]["gt_only"]
    (out / "index.json").write_text(json.dumps(index))
    result = CliRunner().invoke(train_main, ["--labels", str(out), "--out", str(run), "--steps", "1", "--workers", "0"])
    assert result.exit_code == 2 and "is a GT pack" in result.output, result.output

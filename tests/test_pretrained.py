"""The shipped-model plumbing: kitti_unlabelled reader, --init, the Python API, 'pretrained', the JPEG carry pack,
shards without hdf5plugin."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY, make_shards, tiny_config

import optstereo
from optstereo.checkpoint import CheckpointError, load_checkpoint
from optstereo.cli import predict_main, train_main
from optstereo.pretrained import WEIGHTS, resolve_checkpoint_spec
from optstereo.training import loop
from pvm_labeler.common.datasets import discover, load_pair
from pvm_labeler.common.errors import ShardError
from pvm_labeler.shards import schema as shard_schema

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# -- the unlabelled reader ----------------------------------------------------------------------------------------
def _img(path: Path, seed: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.random.default_rng(seed).integers(0, 255, (16, 24, 3), dtype=np.uint8))


def test_unlabelled_reader_finds_every_layout(tmp_path: Path) -> None:
    for i, (left, right) in enumerate([("a/image_2/000001_10.png", "a/image_3/000001_10.png"),
                                       ("b/drive/image_02/data/0000000004.png", "b/drive/image_03/data/0000000004.png"),
                                       ("c/x/image_2/000000.png", "c/x/image_3/000000.png"),
                                       ("d/demo/left.png", "d/demo/right.png")]):
        _img(tmp_path / left, i)
        _img(tmp_path / right, 10 + i)
    _img(tmp_path / "a/disp_noc_0/000001_10.png", 99)  # GT next to the images must never be read
    refs = discover("kitti_unlabelled", tmp_path)
    assert [r.frame_id for r in refs] == ["a-000001_10", "b-drive-0000000004", "c-x-000000", "d-demo"]
    assert all(r.gt is None and r.gt_noc is None for r in refs)
    assert load_pair(refs[0]).gt is None


def test_unlabelled_reader_on_shared_data(shared_data: Path) -> None:
    refs = discover("kitti_unlabelled", shared_data / "kitti_unlabelled")
    assert len(refs) == 87
    gt_ids = {r.frame_id for r in discover("kitti15", shared_data / "kitti15")}
    assert not any(r.frame_id.split("-")[-1] in gt_ids for r in refs if r.frame_id.startswith("kitti15_training"))


# -- --init --------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def trained(tiny_shards: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("init")
    loop.main(tiny_config(tiny_shards, root / "base", steps=2), progress=False)
    return tiny_shards, root / "base"


def test_init_loads_weights_and_starts_a_new_schedule(trained: tuple[Path, Path], tmp_path: Path) -> None:
    shards, base = trained
    result = CliRunner().invoke(train_main, [
        "--labels", str(shards), "--out", str(tmp_path / "ft"), "--init", str(base), "--steps", "1",
        "--crop", "32x64", "--workers", "0", "--iters", "2", "--batch-size", "2", "--quiet"])
    assert result.exit_code == 0, result.output
    ft = load_checkpoint(tmp_path / "ft")
    assert ft.step == 1  # a new run from step 0, not base's step 2
    assert ft.model_config == load_checkpoint(base).model_config  # model settings came from the checkpoint
    assert ft.train_config["init"] == str(base)


def test_init_weights_equal_the_checkpoint(trained: tuple[Path, Path]) -> None:
    _, base = trained
    cfg = tiny_config(Path("unused"), Path("unused"))
    model = loop.build_model(cfg)
    loop.init_weights(model, base)
    for key, value in load_checkpoint(base).model_state.items():
        assert torch.equal(model.state_dict()[key], value), key


def test_init_mismatch_names_the_keys(trained: tuple[Path, Path]) -> None:
    _, base = trained
    wider = loop.build_model(tiny_config(Path("x"), Path("x"), model_overrides={**TINY, "feature_dim": 24}))
    with pytest.raises(CheckpointError, match=r"shape mismatches \['feature_encoder"):
        loop.init_weights(wider, base)
    single = loop.build_model(tiny_config(Path("x"), Path("x"), model="optstereo_ss_d4"))
    with pytest.raises(CheckpointError, match="does not fit the model"):
        loop.init_weights(single, base)


def test_init_and_resume_exclusive(trained: tuple[Path, Path], tmp_path: Path) -> None:
    shards, base = trained
    result = CliRunner().invoke(train_main, ["--init", str(base), "--resume", str(base), "--quiet"])
    assert result.exit_code == 2 and "pick one" in result.output


# -- the Python API and 'pretrained' ----------------------------------------------------------------------------------
def test_api_load_and_predict(trained: tuple[Path, Path]) -> None:
    _, base = trained
    model = optstereo.load_model(base)
    rng = np.random.default_rng(0)
    base_img = rng.integers(0, 256, (30, 90, 3), dtype=np.uint8)
    left, right = base_img[:, 6:], base_img[:, :-6]  # any size: 30 x 84 is padded inside
    disp = optstereo.predict(model, left, right)
    assert disp.shape == (30, 84) and disp.dtype == np.float32
    both = optstereo.predict(model, [(left, right), (left[:20, :70], right[:20, :70])])
    assert [d.shape for d in both] == [(30, 84), (20, 70)]
    np.testing.assert_allclose(both[0], disp, atol=1e-5)
    with pytest.raises(ValueError, match="right image"):
        optstereo.predict(model, left)


def test_pretrained_spec() -> None:
    assert WEIGHTS.is_file(), "the shipped weights must be in the package"
    assert resolve_checkpoint_spec("pretrained") == WEIGHTS
    assert WEIGHTS.stat().st_size <= 12e6
    with pytest.raises(CheckpointError, match="does not exist"):
        resolve_checkpoint_spec("no/such/file.pt")


def test_predict_cli_bad_checkpoint_exits_2(tmp_path: Path) -> None:
    _img(tmp_path / "a.png", 0)
    _img(tmp_path / "b.png", 1)
    result = CliRunner().invoke(predict_main, ["--checkpoint", "missing.pt", str(tmp_path / "a.png"),
                                               str(tmp_path / "b.png"), "--out", str(tmp_path)])
    assert result.exit_code == 2 and "missing.pt" in result.output


# -- shards without the Blosc plugin ------------------------------------------------------------------------------
def test_blosc_without_plugin_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(shard_schema, "hdf5plugin", None)
    with pytest.raises(ShardError, match="needs the hdf5plugin package"):
        make_shards(tmp_path / "s", n=1, shard_size=1)


def test_lzf_shards_need_no_plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from pvm_labeler.shards import ShardRecord, open_shard, read_sample, write_shard_dir

    monkeypatch.setattr(shard_schema, "hdf5plugin", None)
    img = np.zeros((8, 16, 3), np.uint8)
    lab = np.full((8, 16), 2.0, np.float32)
    out = write_shard_dir(tmp_path / "lzf", [ShardRecord("a", img, img, lab, lab, np.ones_like(lab))],
                          compression="lzf")
    with open_shard(out / "shard-00000.h5") as h5:
        assert np.array_equal(read_sample(h5, "a").label, lab)


def test_blosc_shard_without_plugin_names_the_fix(tmp_path: Path) -> None:
    """A reader without hdf5plugin gets HDF5's plugin-directory error translated: the filter and the fix."""
    import subprocess
    import sys

    shards = make_shards(tmp_path / "blosc", n=1, shard_size=1)  # Blosc-LZ4, the default
    code = ("import sys; sys.modules['hdf5plugin'] = None\n"  # as on a machine without the package
            "from pvm_labeler.shards import verify\n"
            f"print('\\n'.join(verify({str(shards)!r})))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "compressed with Blosc" in out and "pvm-label convert" in out and "pip install hdf5plugin" in out

"""Paths read from files stay where they belong (issue 51, item 3): an ``index.json`` names shards inside its own
folder only, a frame id from a shard names files inside the output folder only, and an ONNX file's external data
must sit beside it. docs/bad_input.md lists each case with its message."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import make_shards, make_synthetic_pair

from optstereo.checkpoint import CheckpointError
from optstereo.cli import eval_main, predict_main
from optstereo.inference.confidence import write_confidence
from optstereo.inference.outputs import write_disparity
from optstereo.training.distill import map_path
from pvm_labeler.cli import main as pvm_main
from pvm_labeler.common.datasets import safe_stem
from pvm_labeler.common.errors import ShardError
from pvm_labeler.common.io import write_image
from pvm_labeler.shards import ShardRecord, read_index, write_shard_dir


def _files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


class TestIndexEntries:
    @pytest.mark.parametrize("where", ["parent", "absolute"])
    def test_a_shard_outside_the_folder_is_refused(self, tmp_path: Path, where: str) -> None:
        shards = make_shards(tmp_path / "s", n=2, shard_size=2, height=8, width=16)
        elsewhere = tmp_path / "elsewhere"
        elsewhere.mkdir()
        shutil.copy(shards / "shard-00000.h5", elsewhere / "shard-00000.h5")
        name = "../elsewhere/shard-00000.h5" if where == "parent" else str(elsewhere / "shard-00000.h5")
        doc = json.loads((shards / "index.json").read_text())
        doc["shards"][0]["file"] = name
        (shards / "index.json").write_text(json.dumps(doc))
        with pytest.raises(ShardError, match=r"index\.json: lists shard .*elsewhere/shard-00000\.h5.*not a file "
                                             r"inside"):
            read_index(shards)
        result = CliRunner().invoke(eval_main, ["--labels", str(shards), "--out", str(tmp_path / "e")])
        assert result.exit_code == 1 and "not a file inside" in result.output and "elsewhere" in result.output
        assert not (tmp_path / "e" / "summary.json").exists()

    def test_a_malformed_entry_is_named(self, tmp_path: Path) -> None:
        shards = make_shards(tmp_path / "s", n=2, shard_size=2, height=8, width=16)
        doc = json.loads((shards / "index.json").read_text())
        doc["shards"][0] = {"samples": ["frame-000"]}
        (shards / "index.json").write_text(json.dumps(doc))
        with pytest.raises(ShardError, match=r"a shard entry must hold 'file' \(a name\) and 'samples'"):
            read_index(shards)


@pytest.fixture
def odd_ids(tmp_path: Path) -> tuple[Path, list[str]]:
    """A shard dir whose frame ids lead out of a folder: ``../../escape`` and an absolute path under tmp_path."""
    rng = np.random.default_rng(0)
    ids = ["../../escape", f"{tmp_path}/abs/escape", "plain"]
    records = []
    for i in range(len(ids)):  # the writer refuses such ids now: written plain, then renamed by hand as anyone can
        left, right = make_synthetic_pair(rng, 8, 16, 2)
        label = np.full((8, 16), 2.0, np.float32)
        records.append(ShardRecord(f"f{i}", left, right, label, label, np.ones((8, 16), np.float32), gt=label))
    out = write_shard_dir(tmp_path / "run" / "shards", records, config={"k": 1}, shard_size=3)
    with h5py.File(out / "shard-00000.h5", "r+") as h5:
        for i, frame_id in enumerate(ids):
            h5.move(f"f{i}", frame_id)
        h5.attrs["samples"] = json.dumps(ids)
    index = json.loads((out / "index.json").read_text())
    index["shards"][0]["samples"] = ids
    (out / "index.json").write_text(json.dumps(index))
    return out, ids


class TestFrameIds:
    def test_safe_stem(self) -> None:
        for plain in ("000000_10", "frame-001", "my frame", "a..b"):
            assert safe_stem(plain) == plain  # what the readers and LEFT's stem give: unchanged
        assert safe_stem("../../escape") == "escape"
        assert safe_stem("/abs/escape") == "abs-escape"
        assert safe_stem("..") == "frame"

    def test_eval_maps_stay_in_out(self, odd_ids: tuple[Path, list[str]], tmp_path: Path) -> None:
        shards, _ = odd_ids
        out = tmp_path / "run" / "eval" / "out"
        before = _files(tmp_path)
        result = CliRunner().invoke(eval_main, ["--labels", str(shards), "--out", str(out), "--save-maps", "--quiet"])
        assert result.exit_code == 0, result.output
        new = _files(tmp_path) - before
        assert new and all(out in p.parents for p in new), sorted(map(str, new))
        names = {p.name for p in (out / "maps").iterdir()}
        assert {"escape_disp.png", f"{safe_stem(str(tmp_path))}-abs-escape_error.png", "plain_disp.png"} <= names

    def test_report_pictures_stay_in_out(self, odd_ids: tuple[Path, list[str]], tmp_path: Path) -> None:
        shards, _ = odd_ids
        out = tmp_path / "run" / "rep"
        before = _files(tmp_path)
        result = CliRunner().invoke(pvm_main, ["report", str(shards), "--out", str(out), "--pictures", "3"])
        assert result.exit_code == 0, result.output
        new = _files(tmp_path) - before
        assert new and all(out in p.parents for p in new), sorted(map(str, new))

    def test_disparity_confidence_and_teacher_files_stay_in_out(self, tmp_path: Path) -> None:
        out = tmp_path / "a" / "b"
        disp = np.ones((4, 6), np.float32)
        paths = {**write_disparity(out, "../../x", disp, ["npy", "png"]),
                 **write_disparity(out, "../y", disp, ["pfm"], kitti_layout=True),
                 **write_confidence(out, "/z", disp, ["conf-npy"])}
        assert all(out in p.parents for p in paths.values()), paths
        assert _files(tmp_path) == set(paths.values())
        assert map_path(out, "../../t").parent == out


class TestOnnxExternalData:
    """An ONNX file may name other files holding its tensors; only files beside it are read."""

    @pytest.fixture
    def graph(self, tmp_path: Path):
        onnx = pytest.importorskip("onnx")
        pytest.importorskip("onnxruntime")
        from onnx import TensorProto, helper, numpy_helper

        weights = numpy_helper.from_array(np.arange(4, dtype=np.float32), "w")
        model = helper.make_model(
            helper.make_graph([helper.make_node("Add", ["x", "w"], ["y"])], "g",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [4])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [4])], [weights]),
            opset_imports=[helper.make_opsetid("", 18)])
        (tmp_path / "model").mkdir()
        for where in (tmp_path / "outside.bin", tmp_path / "model" / "inside.bin"):
            np.arange(4, dtype=np.float32).tofile(where)

        def with_location(location: str) -> Path:
            tensor = model.graph.initializer[0]
            tensor.ClearField("raw_data")
            tensor.ClearField("float_data")
            del tensor.external_data[:]
            tensor.data_location = TensorProto.EXTERNAL
            for key, value in (("location", location), ("offset", "0"), ("length", "16")):
                entry = tensor.external_data.add()
                entry.key, entry.value = key, value
            path = tmp_path / "model" / "m.onnx"
            path.write_bytes(model.SerializeToString())
            return path

        return onnx, with_location

    def test_outside_refused_beside_read(self, graph, tmp_path: Path) -> None:
        from optstereo.export import onnx_session

        _, with_location = graph
        for location in ("../outside.bin", str(tmp_path / "outside.bin")):
            with pytest.raises(CheckpointError, match=rf"m\.onnx: tensor 'w' keeps its data in '{location}', "
                                                      r"outside the file's folder"):
                onnx_session(with_location(location))
        session = onnx_session(with_location("inside.bin"))
        np.testing.assert_array_equal(session.run(None, {"x": np.ones(4, np.float32)})[0], [1, 2, 3, 4])

    def test_predict_names_the_file(self, graph, tmp_path: Path) -> None:
        _, with_location = graph
        onnx_file = with_location("../outside.bin")
        image = np.zeros((16, 32, 3), np.uint8)
        write_image(tmp_path / "l.png", image)
        write_image(tmp_path / "r.png", image)
        result = CliRunner().invoke(predict_main, ["--backend", "onnxruntime", "--checkpoint", str(onnx_file),
                                                   str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--out",
                                                   str(tmp_path / "o"), "--format", "npy", "--quiet"])
        assert result.exit_code == 1
        assert "m.onnx: tensor 'w' keeps its data in '../outside.bin', outside the file's folder" in result.output

    def test_not_onnx(self, graph, tmp_path: Path) -> None:
        from optstereo.export import onnx_session

        junk = tmp_path / "junk.onnx"
        junk.write_bytes(b"\x01\x02junk" * 100)
        with pytest.raises(CheckpointError, match=r"cannot read ONNX file .*junk\.onnx"):
            onnx_session(junk)

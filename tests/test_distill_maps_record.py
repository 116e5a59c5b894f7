"""optstereo-distill maps / fill as a user meets them: the teacher recorded in the maps folder (another teacher
refused, an earlier version's folder resumed), a progress bar, pairs with unreadable images skipped and listed, and
fill's label density and missing-map error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY, make_shards, make_synthetic_pair

from optstereo.checkpoint import export_safetensors
from optstereo.cli import distill_main
from optstereo.models import build_model
from optstereo.training import distill
from pvm_labeler.common.io import write_image
from pvm_labeler.shards import INDEX_NAME, read_index

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _teacher(path: Path, seed: int) -> Path:
    torch.manual_seed(seed)
    export_safetensors(path, build_model("optstereo", **TINY, iters=1))
    return path


def _pairs(root: Path, names: list[str]) -> Path:
    rng = np.random.default_rng(0)
    for name in names:
        left, right = make_synthetic_pair(rng, 32, 64, 4)
        write_image(root / "left" / f"{name}.png", left)
        write_image(root / "right" / f"{name}.png", right)
    return root


def _maps(root: Path, teacher: Path, out: Path, *extra: str):  # noqa: ANN202 (click's Result)
    return CliRunner().invoke(distill_main, ["maps", "--checkpoint", str(teacher), "--root", str(root), "--out",
                                             str(out), *extra])


def test_maps_records_its_teacher_and_refuses_another(tmp_path: Path) -> None:
    root = _pairs(tmp_path / "pairs", ["a"])
    first, other = _teacher(tmp_path / "first.safetensors", 0), _teacher(tmp_path / "other.safetensors", 1)
    out = tmp_path / "maps"
    done = _maps(root, first, out)
    assert done.exit_code == 0, done.output
    assert "1/1" in done.output  # the progress bar, on a stream that is not a terminal too
    record = json.loads((out / distill.RECORD).read_text())
    assert record["spec"] == str(first) and len(record["digest"]) == 16 and record["sha256"]
    assert record["inference"]["scale"] == 1.0 and record["amp"] == "none"
    again = _maps(root, first, out, "--quiet")
    assert again.exit_code == 0 and "0 new teacher maps" in again.output
    assert "1/1" not in again.output  # --quiet: no bar
    refused = _maps(root, other, out)
    assert refused.exit_code == 2, refused.output
    assert str(first) in refused.output and str(other) in refused.output and "another --out" in refused.output
    assert json.loads((out / distill.RECORD).read_text()) == record  # the record is left as it was


def test_maps_of_an_earlier_version_resume_with_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A folder of .npz maps without a record: resumed (its maps kept), warned about, then recorded."""
    root = _pairs(tmp_path / "pairs", ["a", "b"])
    out = tmp_path / "maps"
    out.mkdir()
    np.savez(distill.map_path(out, "a"), left=np.full((32, 64), 3.0, np.float32),
             right=np.full((32, 64), 3.0, np.float32))
    done = _maps(root, _teacher(tmp_path / "t.safetensors", 0), out)
    assert done.exit_code == 0, done.output
    assert "1 new teacher map (" in done.output
    assert "cannot be checked" in caplog.text
    assert json.loads((out / distill.RECORD).read_text())["unrecorded_maps"] == 1


def test_maps_skips_and_lists_unreadable_pairs(tmp_path: Path) -> None:
    root = _pairs(tmp_path / "pairs", ["a", "b", "c"])
    good = (root / "left" / "b.png").read_bytes()
    (root / "left" / "b.png").write_bytes(b"not a png")
    teacher, out = _teacher(tmp_path / "t.safetensors", 0), tmp_path / "maps"
    done = _maps(root, teacher, out, "--quiet")
    assert done.exit_code == 1, done.output
    assert "2 new teacher maps" in done.output and "first b" in done.output
    assert distill.map_path(out, "a").is_file() and distill.map_path(out, "c").is_file()
    failures = json.loads((out / distill.FAILURES).read_text())
    assert [f["frame_id"] for f in failures] == ["b"] and "b.png" in failures[0]["error"]
    (root / "left" / "b.png").write_bytes(good)  # mended: the re-run makes only its map and clears the list
    again = _maps(root, teacher, out, "--quiet")
    assert again.exit_code == 0, again.output
    assert "1 new teacher map (" in again.output and not (out / distill.FAILURES).exists()


def test_two_runs_into_one_folder_keep_each_others_failures(tmp_path: Path) -> None:
    """G4's split: two runs over different pairs write one MAPS folder; each run's list keeps the other's records,
    and a mended pair leaves the list while the other run's failure stays."""
    first, second = _pairs(tmp_path / "p1", ["a", "b"]), _pairs(tmp_path / "p2", ["c", "d"])
    good = (first / "left" / "b.png").read_bytes()
    (first / "left" / "b.png").write_bytes(b"not a png")
    (second / "left" / "d.png").write_bytes(b"not a png")
    teacher, out = _teacher(tmp_path / "t.safetensors", 0), tmp_path / "maps"
    assert _maps(first, teacher, out, "--quiet").exit_code == 1
    assert _maps(second, teacher, out, "--quiet").exit_code == 1
    assert sorted(f["frame_id"] for f in json.loads((out / distill.FAILURES).read_text())) == ["b", "d"]
    (first / "left" / "b.png").write_bytes(good)
    assert _maps(first, teacher, out, "--quiet").exit_code == 0
    assert [f["frame_id"] for f in json.loads((out / distill.FAILURES).read_text())] == ["d"]


def test_a_corrupt_failures_list_is_replaced(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = _pairs(tmp_path / "pairs", ["a"])
    out = tmp_path / "maps"
    out.mkdir()
    (out / distill.FAILURES).write_text("{not json")
    assert _maps(root, _teacher(tmp_path / "t.safetensors", 0), out, "--quiet").exit_code == 0
    assert not (out / distill.FAILURES).exists() and "failures.json: unreadable" in caplog.text


def _constant_maps(shards: Path, out: Path, skip: str | None = None) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    for _, ids in read_index(shards).shards:
        for frame_id in ids:
            if frame_id != skip:
                np.savez(distill.map_path(out, frame_id), left=np.full((32, 64), 3.0, np.float32),
                         right=np.full((32, 64), 3.0, np.float32))
    return out


def test_fill_reports_the_density_and_records_the_teacher(tmp_path: Path) -> None:
    shards = make_shards(tmp_path / "labels", n=2, with_gt=False)
    doc = json.loads((shards / INDEX_NAME).read_text())
    doc["summary"] = {"label_fraction": 42.4, "pairs_total": 2}
    (shards / INDEX_NAME).write_text(json.dumps(doc))
    maps = _constant_maps(shards, tmp_path / "maps")
    record = {"spec": "pretrained", "digest": "0123456789abcdef", "inference": {}, "amp": "none"}
    (maps / distill.RECORD).write_text(json.dumps(record))
    done = CliRunner().invoke(distill_main, ["fill", str(shards), str(maps), str(tmp_path / "filled")])
    assert done.exit_code == 0, done.output
    # PVM labels x >= 4 of 64 columns; the teacher's 3 px views agree from x = 3: one more column
    assert "label density 93.8 % -> 95.3 %" in done.output and "teacher pretrained" in done.output
    raw = read_index(tmp_path / "filled").raw
    assert raw["summary"] == {"label_fraction": pytest.approx(100 * 61 / 64), "pairs_total": 2,
                              "label_fraction_pvm": pytest.approx(100 * 60 / 64)}
    assert raw["distill"]["teacher"] == record
    (maps / distill.RECORD).unlink()  # maps of an earlier version: filled all the same, teacher unrecorded
    done = CliRunner().invoke(distill_main, ["fill", str(shards), str(maps), str(tmp_path / "filled_old")])
    assert done.exit_code == 0, done.output
    assert read_index(tmp_path / "filled_old").raw["distill"]["teacher"] is None


def test_fill_names_a_missing_map_and_allow_missing(tmp_path: Path) -> None:
    shards = make_shards(tmp_path / "labels", n=2, with_gt=False)
    maps = _constant_maps(shards, tmp_path / "maps", skip="frame-001")
    done = CliRunner().invoke(distill_main, ["fill", str(shards), str(maps), str(tmp_path / "filled")])
    assert done.exit_code == 1
    assert "frame-001" in done.output and "--allow-missing" in done.output and "optstereo-distill maps" in done.output
    assert not (tmp_path / "filled" / INDEX_NAME).exists()
    done = CliRunner().invoke(distill_main, ["fill", str(shards), str(maps), str(tmp_path / "filled"),
                                             "--allow-missing"])
    assert done.exit_code == 0, done.output


def test_maps_takes_device_auto_as_every_command_does(tmp_path: Path) -> None:
    """--device auto (the default now, as in eval / predict / train): it was refused as not one of cpu, cuda; without
    CUDA, --device cuda says so naming the fix."""
    root = _pairs(tmp_path / "pairs", ["a"])
    teacher = _teacher(tmp_path / "t.safetensors", 0)
    done = _maps(root, teacher, tmp_path / "maps", "--device", "auto", "--quiet")
    assert done.exit_code == 0 and "1 new teacher map" in done.output, done.output
    assert np.load(tmp_path / "maps" / "a.npz")["left"].shape == (32, 64)
    if not torch.cuda.is_available():
        refused = _maps(root, teacher, tmp_path / "maps2", "--device", "cuda", "--quiet")
        assert refused.exit_code == 1 and "use device cpu (or auto)" in refused.output, refused.output

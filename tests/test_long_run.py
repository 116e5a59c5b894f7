"""Issue 49.3's chaptered run (pipelines/studies/long_run.py): a chapter trains only on the pairs that have the
teacher's maps, and the learning curve adds up steps and hours over chapters, a resumed chapter counted once."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import make_shards

from pipelines.studies import long_run
from pvm_labeler.shards.reader import read_index


def _maps(folder: Path, ids: list[str]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for frame_id in ids:
        np.savez(folder / f"{frame_id}.npz", left=np.zeros((2, 2), np.float32), right=np.zeros((2, 2), np.float32))
    return folder


def test_only_the_pairs_with_maps_train(tmp_path: Path) -> None:
    shards = make_shards(tmp_path / "labels", n=5, shard_size=1, with_gt=False)
    maps = _maps(tmp_path / "maps", ["frame-001", "frame-003"])
    selected = long_run.with_maps(shards, maps)
    assert [ids for _, ids in selected] == [["frame-001"], ["frame-003"]]
    assert long_run.merge_shards(tmp_path / "train", selected, shards) == 2
    index = read_index(tmp_path / "train")
    assert [ids for _, ids in index.shards] == [["frame-001"], ["frame-003"]]
    assert index.num_samples == 2 and all(path.is_file() for path, _ in index.shards)


def test_a_shard_with_one_pair_missing_its_map_is_left_out(tmp_path: Path) -> None:
    shards = make_shards(tmp_path / "labels", n=4, shard_size=2, with_gt=False)
    maps = _maps(tmp_path / "maps", ["frame-000", "frame-001", "frame-002"])
    assert [ids for _, ids in long_run.with_maps(shards, maps)] == [["frame-000", "frame-001"]]


def _ledger_line(chapter: str, steps: int, hours: float, val: list[tuple[int, float]], resumed: bool = False) -> dict:
    return {"chapter": chapter, "resumed": resumed, "steps": steps, "hours": hours,
            "machine": {"gpu": None, "isa": "avx2"},
            "val": [{"step": s, "gtfree_pvm_epe": e} for s, e in val]}


def test_curve_adds_up_chapters(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    lines = [_ledger_line("ch01", 200, 1.0, [(0, 0.519), (100, 0.52), (200, 0.51)]),  # step 0: its --init's score
             # ch02 cut off at step 100 of its own run, then resumed: the second line holds its whole metrics.jsonl
             _ledger_line("ch02", 100, 0.5, [(100, 0.50)]),
             _ledger_line("ch02", 300, 1.0, [(100, 0.50), (200, 0.49), (300, 0.48)], resumed=True)]
    (run / long_run.LEDGER).write_text("".join(json.dumps(line) + "\n" for line in lines))
    rows = long_run.curve(run, tmp_path / "out", start={"gtfree_pvm_epe": 0.519})
    assert [r["step"] for r in rows] == [0, 100, 200, 300, 400, 500]
    assert [r["gtfree_pvm_epe"] for r in rows] == [0.519, 0.52, 0.51, 0.50, 0.49, 0.48]
    assert rows[-1]["hours"] == 2.5
    assert (tmp_path / "out" / "curve.png").stat().st_size > 0
    assert "| ch02 | avx2 | 500 | 2.5 |  | 0.4800 |" in (tmp_path / "out" / "curve.md").read_text()


def _gtfree(errs: list[float], photo: list[float]) -> dict:
    pairs = [{"frame_id": f"p{i}", "pvm_n": 100, "pvm_err": 100 * e, "pvm_bad": 0, "photo_sum": 100 * f, "photo_n": 100}
             for i, (e, f) in enumerate(zip(errs, photo, strict=True))]
    return {"summary": {"pvm_epe": sum(errs) / len(errs)}, "pairs": pairs}


def test_the_rule_needs_a_gain_beyond_noise() -> None:
    base = _gtfree([0.5, 0.6, 0.7, 0.8], [0.1] * 4)
    # lower on every pair by 0.05 +- 0.01: mean -0.05, margin 2 * 0.0129 / 2 = 0.0129 -> a candidate
    assert long_run.candidate(base, _gtfree([0.44, 0.56, 0.64, 0.76], [0.1] * 4))[0]
    # the same mean gain, but one pair carries it: inside the noise
    assert not long_run.candidate(base, _gtfree([0.3, 0.6, 0.7, 0.8], [0.1] * 4))[0]
    # lower EPE but a photometric error worse on every pair
    ok, why = long_run.candidate(base, _gtfree([0.44, 0.56, 0.64, 0.76], [0.11, 0.12, 0.11, 0.12]))
    assert not ok and why.startswith("not a candidate")


def test_record_appends_a_gpu_chapter_scored_here(tmp_path: Path) -> None:
    """Snapshots sent back by a lent GPU become a chapter: each scored on the validation set by optstereo-eval, the
    last one the weights the next chapter starts from."""
    import torch
    from conftest import TINY, make_valset

    from optstereo.checkpoint import export_safetensors
    from optstereo.models import build_model

    val = make_valset(tmp_path / "val", teacher_digest="none")
    torch.manual_seed(0)
    snaps = [tmp_path / "G-4.safetensors", tmp_path / "G-2.safetensors"]
    for snap in snaps:
        export_safetensors(snap, build_model("optstereo", **TINY, iters=1))
    run = tmp_path / "run"
    chapter = long_run.record(run, snaps, val, "NVIDIA H100", 0.2)
    line = json.loads((run / long_run.LEDGER).read_text())
    assert chapter.name == "ch01" and line["machine"]["gpu"] == "NVIDIA H100" and line["steps"] == 4
    assert [row["step"] for row in line["val"]] == [2, 4] and line["val"][0]["gtfree_pairs"] == 3.0
    assert (chapter / "run" / "model.safetensors").read_bytes() == snaps[0].read_bytes()
    rows = long_run.curve(run, tmp_path / "curve")
    assert [(r["machine"], r["step"]) for r in rows] == [("NVIDIA H100", 2), ("NVIDIA H100", 4)]


def test_record_checks_names_first_and_leaves_no_half_chapter(tmp_path: Path) -> None:
    """A snapshot not named <name>-<step> is refused before anything is made; a snapshot the evaluation cannot read
    leaves no chapter folder behind (it blocked every later record and chapter as "unfinished")."""
    from conftest import make_valset

    val, run = make_valset(tmp_path / "val", teacher_digest="none"), tmp_path / "run"
    plain = tmp_path / "model.safetensors"
    plain.write_bytes(b"x")
    with pytest.raises(SystemExit, match="named <name>-<step>.safetensors"):
        long_run.record(run, [plain], val, "NVIDIA H100", 0.1)
    assert not run.exists()
    broken = tmp_path / "G-2.safetensors"
    broken.write_bytes(b"not weights")
    with pytest.raises(SystemExit, match="record.log"):
        long_run.record(run, [broken], val, "NVIDIA H100", 0.1)
    assert sorted(p.name for p in run.iterdir()) == ["record.log"]  # no ch01: the next record or chapter can run


def test_hours_count_a_cut_off_session_to_its_last_checkpoint(tmp_path: Path) -> None:
    """A chapter's hours: a session cut off (no ledger line) counts up to its last.pt, the next one to its end."""
    import os

    current, out = tmp_path / "ch01", tmp_path / "ch01" / "run"
    out.mkdir(parents=True)
    long_run.session_hours(current, out)  # cut off: its total is never taken
    start = json.loads((current / "sessions.json").read_text())[0][0]
    (out / "last.pt").write_bytes(b"")
    os.utime(out / "last.pt", (start + 3600, start + 3600))  # its last checkpoint an hour in
    total = long_run.session_hours(current, out)
    assert 1.0 <= total() < 1.01
    spans = json.loads((current / "sessions.json").read_text())
    assert spans[0] == [start, start + 3600] and len(spans) == 2


def test_compare_refuses_reports_of_other_pairs(tmp_path: Path) -> None:
    base, cand = _gtfree([0.5, 0.6, 0.7, 0.8], [0.1] * 4), _gtfree([0.5, 0.6], [0.1] * 2)
    for name, doc in (("base.json", base), ("cand.json", cand)):
        (tmp_path / name).write_text(json.dumps(doc))
    with pytest.raises(SystemExit, match=r"scores 4 pairs, .*cand.json 2 \(2 shared\): compare reports of the same"):
        long_run.main(["compare", str(tmp_path / "base.json"), str(tmp_path / "cand.json")])
    with pytest.raises(SystemExit, match="missing.json: not a readable optstereo-eval --valset report"):
        long_run.main(["compare", str(tmp_path / "missing.json"), str(tmp_path / "cand.json")])


def test_a_chapter_end_to_end_then_the_next_from_its_weights(tmp_path: Path) -> None:
    """Two chapters on a folder of 3 pairs, 2 with teacher maps: the labeler, the fill, the merge of the 2 pairs with
    maps, the trainer with the validation set, a ledger line each; the second starts from the first's weights."""
    import shutil
    from argparse import Namespace

    import torch
    from conftest import TINY, make_folder, make_valset

    from optstereo.checkpoint import export_safetensors
    from optstereo.models import build_model

    pack = make_folder(tmp_path / "pack", n=3, size=(64, 128))
    shutil.rmtree(pack / "gt")  # unlabelled pairs
    maps = tmp_path / "maps"
    maps.mkdir()
    for frame_id in ("000", "002"):
        np.savez(maps / f"{frame_id}.npz", left=np.full((64, 128), 4.0, np.float32),
                 right=np.full((64, 128), 4.0, np.float32))
    torch.manual_seed(0)
    init = tmp_path / "init.safetensors"
    export_safetensors(init, build_model("optstereo", **TINY, iters=1))
    args = Namespace(run=tmp_path / "run", packs=[pack], maps=maps, valset=make_valset(tmp_path / "val", "none"),
                     init=str(init), minutes=0.02, ckpt_every=1, threads=1, jobs=1, val_limit=0, max_disp=16)
    first = long_run.chapter(args)
    assert [ids for _, ids in read_index(first / "train").shards] == [["000"], ["002"]]
    second = long_run.chapter(args)
    assert json.loads((second / "start.json").read_text())["init"] == str(first / "run" / "model.safetensors")
    lines = [json.loads(t) for t in (args.run / long_run.LEDGER).read_text().splitlines()]
    assert [(line["chapter"], line["pairs"]) for line in lines] == [("ch01", 2), ("ch02", 2)]
    assert all(line["steps"] >= 1 and line["val"] and line["val"][0]["gtfree_pairs"] == 3.0 for line in lines)


def test_teacher_all_merge_lists_every_shard_of_every_source(tmp_path: Path) -> None:
    """The GPU study's merge is the same function over all shards: one index, the sources recorded."""
    from pipelines.studies.gpu import teacher_all

    a = make_shards(tmp_path / "a", n=2, shard_size=1, with_gt=False)
    b = make_shards(tmp_path / "b", n=3, shard_size=2, with_gt=False, seed=1)
    assert teacher_all.merge(tmp_path / "all", [a, b]) == 5
    index = read_index(tmp_path / "all")
    assert [len(ids) for _, ids in index.shards] == [1, 1, 2, 1]
    assert index.raw["merged_from"] == [str(a), str(b)]


def test_teacher_all_merge_with_maps_drops_the_shards_the_teacher_missed(tmp_path: Path) -> None:
    """MISSING=drop: a shard with one pair the teacher's box did not reach does not train (G1 and G3 kept them)."""
    from pipelines.studies.gpu import teacher_all

    a = make_shards(tmp_path / "a", n=4, shard_size=2, with_gt=False)
    maps = _maps(tmp_path / "maps", ["frame-000", "frame-001", "frame-003"])
    assert teacher_all.merge(tmp_path / "all", [a], maps) == 2
    index = read_index(tmp_path / "all")
    assert [ids for _, ids in index.shards] == [["frame-000", "frame-001"]]
    assert index.raw["only_pairs_with_maps_in"] == str(maps)
    assert teacher_all.merge(tmp_path / "every", [a]) == 4


def test_coverage_counts_maps_and_the_pixels_both_views_agree_on(tmp_path: Path) -> None:
    import cv2

    pack = tmp_path / "pack"
    for side in ("left", "right"):
        (pack / side).mkdir(parents=True)
        for name in ("a", "b"):
            cv2.imwrite(str(pack / side / f"{name}.png"), np.zeros((2, 4, 3), np.uint8))
    maps = tmp_path / "maps"
    maps.mkdir()
    # pair a: constant disparity 1 in both views. Left columns 1..3 find their match (x - 1) in the right view;
    # column 0 looks off the image: 6 of 8 left pixels agree. Pair b has no map.
    ones = np.ones((2, 4), np.float32)
    np.savez(maps / "a.npz", left=ones, right=ones)
    rows = long_run.coverage([pack], maps, tmp_path / "out")
    assert rows == [{"pack": "pack", "pairs": 2, "maps": 1, "consistent": 0.75}]
    table = (tmp_path / "out" / "maps_coverage.md").read_text()
    assert "| pack | 2 | 1 | 75.0 % |" in table and "| all | 2 | 1 | |" in table
    assert json.loads((tmp_path / "out" / "maps_coverage.json").read_text()) == rows
    assert (tmp_path / "out" / "maps_examples.png").stat().st_size > 0

"""pipelines.studies.recipe_table end to end on a tiny model: tiny shards, a handmade GT-free validation set, a few
seconds per recipe; a second call reuses every finished recipe."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY, make_shards

from optstereo import validation
from optstereo.checkpoint import export_safetensors, load_checkpoint
from optstereo.models import build_model
from optstereo.training import distill
from pipelines.studies import recipe_table
from pvm_labeler.common.atomic import atomic_write_text
from pvm_labeler.shards import read_index


def _valset(root: Path) -> Path:
    """Three tiny pairs without GT, teacher maps of constant 3 px, a manifest naming another teacher."""
    make_shards(root / "labels", n=3, width=72, with_gt=False, compression="lzf")
    (root / "maps").mkdir(parents=True)
    for _, ids in read_index(root / "labels").shards:
        for frame_id in ids:
            np.savez(distill.map_path(root / "maps", frame_id), left=np.full((32, 72), 3.0, np.float32),
                     right=np.full((32, 72), 3.0, np.float32))
    atomic_write_text(root / validation.MANIFEST, json.dumps({"teacher": {"digest": "someone-else"}}))
    return root


def test_half_area_keeps_the_aspect_on_the_8_grid() -> None:
    assert recipe_table.half_area((256, 640)) == (184, 456)  # 51 % of the area
    assert recipe_table.fixed_crop((375, 1242), (256, 640)) == (slice(119, 375), slice(301, 941))


def test_table_end_to_end_and_resumes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    labels = make_shards(tmp_path / "labels", n=4, height=32, width=72, with_gt=False)
    valset = _valset(tmp_path / "val")
    torch.manual_seed(0)
    init = export_safetensors(tmp_path / "init.safetensors", build_model("optstereo", **TINY, iters=2))
    argv = ["--labels", str(labels), "--valset", str(valset), "--init", str(init), "--minutes", "0.05",
            "--out", str(tmp_path / "out"), "--recipes", "whole,frozen,cached,bf16", "--threads", "1"]
    rows = {row["recipe"]: row for row in recipe_table.main(argv)}
    assert list(rows) == ["init", "whole", "frozen", "cached", "bf16"]
    for name in ("whole", "frozen", "cached"):
        assert rows[name]["steps"] >= 1 and rows[name]["steps_per_s"] > 0, rows[name]
        assert np.isfinite(rows[name]["pvm_epe"]) and np.isfinite(rows[name]["photometric"])
    assert np.isfinite(rows["init"]["pvm_bad3"])
    assert len(list((tmp_path / "out" / "cached" / "cache").glob("*.npz"))) == 4
    from optstereo.inference.engine import cpu_has_native_bf16
    assert ("steps" in rows["bf16"]) == cpu_has_native_bf16()
    table = (tmp_path / "out" / "table.md").read_text()
    assert "| frozen | encoder frozen |" in table
    start, frozen, whole = (load_checkpoint(p).model_state for p in
                            (init, tmp_path / "out" / "frozen" / "model.safetensors",
                             tmp_path / "out" / "whole" / "model.safetensors"))
    encoder = [k for k in start if k.startswith("feature_encoder.")]
    assert all(torch.equal(frozen[k], start[k]) for k in encoder)  # the frozen run kept its encoder
    assert not all(torch.equal(whole[k], start[k]) for k in encoder)  # the whole one trained it
    assert json.loads((tmp_path / "out" / "table.json").read_text())["rows"][1]["recipe"] == "whole"

    def no_training(cmd: list[str], threads: int) -> None:
        raise AssertionError(f"finished recipes must be reused, ran {cmd}")

    monkeypatch.setattr(recipe_table, "_run", no_training)
    monkeypatch.setattr(recipe_table, "train_cached", no_training)
    again = recipe_table.main(argv)
    assert [r.get("steps") for r in again] == [r.get("steps") for r in rows.values()]

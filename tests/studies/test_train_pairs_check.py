"""pipelines/studies/train_pairs_check.py: the training pairs it scores are every N-th matching pair WITH a map."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import make_shards

from optstereo.training import distill
from pipelines.studies import train_pairs_check


def test_pick_takes_every_nth_matching_pair_that_has_a_map(tmp_path: Path) -> None:
    labels = make_shards(tmp_path / "labels", n=8, shard_size=3, with_gt=False)
    (tmp_path / "maps").mkdir()
    for i in (0, 1, 2, 4, 5, 6, 7):  # frame-003 has no map
        np.savez(distill.map_path(tmp_path / "maps", f"frame-{i:03d}"), left=np.zeros((2, 2)), right=np.zeros((2, 2)))
    # with maps: 000 001 002 004 005 006 007 -> every 2nd: 000 002 005 007 -> at most 3
    assert train_pairs_check.pick(labels, tmp_path / "maps", "frame", 2, 3) == {"frame-000", "frame-002", "frame-005"}
    assert train_pairs_check.pick(labels, tmp_path / "maps", "nothing", 1, 5) == set()

"""DDP on CPU: two torchrun processes (gloo), tiny model; disjoint shards per rank and weights in sync.

The test launches ``python -m torch.distributed.run --standalone --nproc_per_node 2 tests/test_ddp.py SHARDS OUT``;
run as a script, this file is the per-rank worker (see ``worker``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import TINY, make_shards

REPO = Path(__file__).resolve().parents[1]


def worker(shards: Path, out: Path) -> None:
    """One rank: record the frame ids its stream sees, then train a few DDP steps and report a weight checksum."""
    from optstereo.data.stream import ShardStream
    from optstereo.training.config import TrainConfig
    from optstereo.training.loop import main

    rank, world = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    stream = ShardStream(shards, rank=rank, world_size=world, infinite=False, with_ids=True)
    ids = sorted(item[-1] for item in stream)
    cfg = TrainConfig.from_dict(dict(labels=shards, out=out / "run", steps=3, batch_size=1, crop=(32, 64), workers=1,
                                     iters=2, model_overrides=TINY, log_every=1, ckpt_every=3, image_every=0,
                                     tensorboard=False, device="cpu", seed=0))
    summary = main(cfg)
    (out / f"rank{rank}.json").write_text(json.dumps({"ids": ids, "world": summary["world_size"],
                                                      "checksum": summary["param_checksum"],
                                                      "step": summary["step"]}))


def test_two_ranks_disjoint_shards_weights_in_sync(tmp_path: Path) -> None:
    sys.path.insert(0, str(Path(__file__).parent))

    shards = make_shards(tmp_path / "shards", n=4, shard_size=1, height=32, width=64)
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           str(Path(__file__)), str(shards), str(tmp_path)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    ranks = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    assert ranks[0]["world"] == ranks[1]["world"] == 2 and ranks[0]["step"] == ranks[1]["step"] == 3
    # 4 one-sample shards over 2 ranks x 1 worker: rank 0 reads shards 0 and 2, rank 1 shards 1 and 3.
    assert ranks[0]["ids"] == ["frame-000", "frame-002"] and ranks[1]["ids"] == ["frame-001", "frame-003"]
    # Different data on each rank, yet identical weights: the gradients were all-reduced.
    assert ranks[0]["checksum"] == pytest.approx(ranks[1]["checksum"], rel=0, abs=1e-9)
    assert (tmp_path / "run" / "last.pt").is_file()  # written once, by rank 0


if __name__ == "__main__":
    worker(Path(sys.argv[1]), Path(sys.argv[2]))

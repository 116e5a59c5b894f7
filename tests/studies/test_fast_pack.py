"""pipelines/studies/fast_pack.py (candidate F3's pack): the shared pairs linked, a fetched folder of HALVED written at
half size (the 2x2 block means), byte-identical pairs dropped."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pipelines.studies import fast_pack
from pvm_labeler.common.io import read_image


def test_write_pack_links_and_halves(tmp_path: Path, shared_data: Path) -> None:
    rng = np.random.default_rng(0)
    fetched = tmp_path / "fetched"
    images = {}
    for folder in (fast_pack.HALVED[0], "street"):
        for side in ("image_2", "image_3"):
            (fetched / folder / side).mkdir(parents=True)
            img = rng.integers(0, 256, (8, 12, 3), dtype=np.uint8)
            cv2.imwrite(str(fetched / folder / side / "a.png"), img)
            images[folder, side] = img
    n = fast_pack.write_pack(shared_data, fetched, tmp_path / "pack")
    unique_shared = {fast_pack.file_digest(left) for _, left, _, _ in fast_pack.candidate_pairs(shared_data, None)}
    assert n == len(unique_shared) + 2
    halved = tmp_path / "pack" / "left" / f"fm_{fast_pack.HALVED[0]}_a.png"
    assert not halved.is_symlink()
    blocks = images[fast_pack.HALVED[0], "image_2"].astype(np.float64).reshape(4, 2, 6, 2, 3).mean(axis=(1, 3))
    assert np.abs(cv2.imread(str(halved)).astype(np.float64) - blocks).max() <= 0.5 + 1e-9
    street = tmp_path / "pack" / "left" / "fm_street_a.png"
    assert street.is_symlink()
    np.testing.assert_array_equal(read_image(street), read_image(fetched / "street" / "image_2" / "a.png"))

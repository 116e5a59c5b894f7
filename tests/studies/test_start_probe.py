"""The start probe's cheap SGM start (pipelines/studies/start_probe.py): a shift it must find, in the pair's pixels."""

from __future__ import annotations

import numpy as np

from pipelines.studies.start_probe import sgm_shrunk


def test_sgm_shrunk_finds_a_constant_shift_in_the_pairs_pixels() -> None:
    """A textured image and its copy shifted 12 px: the 4x-shrunk SGM sees 3 px, and the start reads 12 px back at
    full size (away from the left border, where the right image has no match)."""
    rng = np.random.default_rng(0)
    texture = rng.integers(0, 256, (32, 64), np.uint8)
    left = np.repeat(np.repeat(texture, 4, axis=0), 4, axis=1)  # 4x4 blocks: the shrunk pair keeps the texture
    right = np.roll(left, -12, axis=1)  # left(x) matches right(x - 12)
    rgb = [np.repeat(x[..., None], 3, axis=2) for x in (left, right)]
    disp = sgm_shrunk(*rgb, factor=4, max_disp=64)
    assert disp.shape == (128, 256) and disp.dtype == np.float32
    inner = disp[16:-16, 64:-16]
    assert abs(float(np.median(inner)) - 12.0) < 0.05  # sub-pixel refinement: 11.999 here
    assert np.mean(np.abs(inner - 12.0) < 1.0) > 0.9

"""Quality of the PVM labels on real KITTI 2015 (../shared/data/kitti15), default LabelerConfig.

GT: disp_noc_0 where present, else disp_occ_0 (frame 000046); uint16 PNG / 256, 0 = no GT. Metrics pooled over
pixels (pvm_labeler.common.metrics): density = labelled GT-valid pixels / GT-valid pixels, bad-3 and AEPE on the
labelled GT-valid pixels. The baselines use the same matcher at full resolution (pipelines.baselines).
"""

from __future__ import annotations

import math

import pytest

from pipelines.baselines import MATCHED_DENSITIES, load_frames, quality_report
from pvm_labeler.config import LabelerConfig

# The bars on all 15 frames.
FULL_BARS = {"density": 50.0, "bad3": 1.5, "epe": 0.9, "bad3_ratio": 0.5, "density_ratio": 0.55}
# Two frames in the default run: looser, because two frames carry far fewer pixels and their own scene bias
# (000000: urban street, 000046: road with cars). Measured with the defaults: density 59.7 %, bad-3 1.54 %,
# AEPE 0.64 px, x0.43 / x0.70 of SGM + LR (84.7 %, 3.61 %). Still fails on a vote that keeps everything (bad-3 ratio
# ~1), a broken LR check (bad-3 up), or a pyramid/scale error (density collapses). The matched-density comparison
# is only asserted on all 15 frames: on two frames the two curves are within noise of each other at 50 %.
QUICK_FRAMES = ("000000", "000046")
QUICK_BARS = {"density": 45.0, "bad3": 2.0, "epe": 1.0, "bad3_ratio": 0.6, "density_ratio": 0.5}


def _check_bars(report: dict, bars: dict) -> None:
    pvm, ratios = report["pvm"], report["ratios"]
    summary = (f"PVM density {pvm['density']:.1f} %, bad-3 {pvm['bad3']:.2f} %, AEPE {pvm['epe']:.3f} px; "
               f"vs SGM+LR: bad-3 x{ratios['bad3']:.2f}, density x{ratios['density']:.2f}")
    assert pvm["density"] >= bars["density"], summary
    assert pvm["bad3"] <= bars["bad3"], summary
    assert pvm["epe"] <= bars["epe"], summary
    assert ratios["bad3"] <= bars["bad3_ratio"], summary
    assert ratios["density"] >= bars["density_ratio"], summary


def test_kitti15_two_frames(shared_data):
    frames = load_frames("kitti15", shared_data / "kitti15", QUICK_FRAMES)
    report = quality_report(frames, LabelerConfig())
    _check_bars(report, QUICK_BARS)


@pytest.mark.slow
def test_kitti15_all_frames(shared_data):
    frames = load_frames("kitti15", shared_data / "kitti15")
    assert len(frames) == 15
    report = quality_report(frames, LabelerConfig())
    _check_bars(report, FULL_BARS)
    for density in MATCHED_DENSITIES:
        matched = report["matched"][density]
        assert not math.isnan(matched["pvm"]) and not math.isnan(matched["uniq"]), (density, matched)
        assert matched["pvm"] < matched["uniq"], (density, matched)

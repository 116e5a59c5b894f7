"""The metrics ruler: hand-computed values, pooling exactness, NaN conventions."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pvm_labeler.common.errors import InputError
from pvm_labeler.common.metrics import MetricAccumulator, disparity_metrics

NAN = np.nan


class TestDisparityMetrics:
    def test_feature_hand_computed(self) -> None:
        gt = np.array([[10.0, 10.0, 10.0, 100.0], [NAN, 50.0, 20.0, 2.0]], np.float32)
        pred = np.array([[10.5, 11.5, 12.5, 104.0], [5.0, NAN, 20.0, 6.0]], np.float32)
        # GT-valid: 7 px; covered: 6 (gt 50 has no prediction). errors: 0.5 1.5 2.5 4 0 4
        m = disparity_metrics(pred, gt)
        assert m["n_valid"] == 7 and m["n_covered"] == 6
        assert m["density"] == pytest.approx(100 * 6 / 7)
        assert m["epe"] == pytest.approx(12.5 / 6)
        assert m["bad1"] == pytest.approx(100 * 4 / 6)  # 1.5 2.5 4 4
        assert m["bad2"] == pytest.approx(100 * 3 / 6)  # 2.5 4 4
        assert m["bad3"] == pytest.approx(100 * 2 / 6)  # 4 4
        # D1: err > 3 AND err > 5 % gt: (4 vs 100 -> 4 <= 5, not an outlier), (4 vs 2 -> outlier)
        assert m["d1"] == pytest.approx(100 * 1 / 6)

    def test_threshold_is_strict(self) -> None:
        gt = np.zeros((1, 3), np.float32) + 10
        pred = gt + np.array([[1.0, 2.0, 3.0]], np.float32)
        m = disparity_metrics(pred, gt)
        assert m["bad1"] == pytest.approx(100 * 2 / 3) and m["bad3"] == 0.0

    def test_valid_mask(self) -> None:
        gt = np.full((2, 2), 10.0, np.float32)
        pred = np.array([[10.0, 20.0], [10.0, 10.0]], np.float32)
        m = disparity_metrics(pred, gt, valid=np.array([[True, False], [True, True]]))
        assert m["n_valid"] == 3 and m["bad3"] == 0.0 and m["epe"] == 0.0

    def test_empty_is_nan(self) -> None:
        gt = np.full((2, 2), NAN, np.float32)
        m = disparity_metrics(np.zeros((2, 2), np.float32), gt)
        assert m["n_valid"] == 0 and math.isnan(m["density"]) and math.isnan(m["epe"])
        m = disparity_metrics(np.full((2, 2), NAN, np.float32), np.ones((2, 2), np.float32))
        assert m["density"] == 0.0 and math.isnan(m["bad3"])

    def test_inf_prediction_not_covered(self) -> None:
        m = disparity_metrics(np.array([[np.inf, 1.0]]), np.array([[1.0, 1.0]]))
        assert m["density"] == 50.0

    def test_exception(self) -> None:
        with pytest.raises(InputError, match=r"\(2, 3\) differs from GT shape \(2, 2\)"):
            disparity_metrics(np.zeros((2, 3)), np.zeros((2, 2)))
        with pytest.raises(InputError, match="valid mask shape"):
            disparity_metrics(np.zeros((2, 2)), np.zeros((2, 2)), valid=np.zeros((1, 2), bool))


class TestAccumulator:
    def test_pooled_equals_concatenation(self, rng: np.random.Generator) -> None:
        frames = []
        for shape in ((5, 7), (9, 3), (4, 4)):
            gt = rng.uniform(1, 60, shape)
            gt[rng.random(shape) < 0.3] = NAN
            pred = gt + rng.normal(0, 3, shape)
            pred[rng.random(shape) < 0.2] = NAN
            frames.append((pred, gt))
        acc = MetricAccumulator()
        for pred, gt in frames:
            acc.update(pred, gt)
        flat_pred = np.concatenate([p.ravel() for p, _ in frames])[None]
        flat_gt = np.concatenate([g.ravel() for _, g in frames])[None]
        pooled, direct = acc.compute(), disparity_metrics(flat_pred, flat_gt)
        for key in direct:
            assert pooled[key] == pytest.approx(direct[key], rel=1e-12)
        assert acc.n_frames == 3

    def test_merge(self) -> None:
        a, b = MetricAccumulator(), MetricAccumulator()
        a.update(np.array([[1.0]]), np.array([[5.0]]))
        b.update(np.array([[5.0]]), np.array([[5.0]]))
        merged = MetricAccumulator().merge(a).merge(b).compute()
        assert merged["epe"] == 2.0 and merged["bad3"] == 50.0 and merged["n_covered"] == 2


class TestViz:
    def test_error_map_colours(self) -> None:
        from pvm_labeler.common.viz import KITTI_ERROR_BINS, NO_LABEL_RGB, error_map

        gt = np.array([[10.0, 10.0, 10.0, NAN, 100.0]], np.float32)
        pred = np.array([[10.25, NAN, 70.0, 5.0, 104.0]], np.float32)
        img = error_map(pred, gt)
        assert img.shape == (1, 5, 3) and img.dtype == np.uint8
        assert tuple(img[0, 0]) == KITTI_ERROR_BINS[1][2]  # 0.25 px -> min(0.083, 0.5) in [0.0625, 0.125)
        assert tuple(img[0, 1]) == NO_LABEL_RGB  # GT but no prediction
        assert tuple(img[0, 2]) == KITTI_ERROR_BINS[-1][2]  # 60 px -> min(20, 120) >= 16: the last bin
        assert tuple(img[0, 3]) == (0, 0, 0)  # no GT
        # 4 px on gt 100: min(4 / 3, 0.04 / 0.05) = 0.8 -> not an outlier (bin [0.5, 1))
        assert tuple(img[0, 4]) == KITTI_ERROR_BINS[4][2]

    def test_colorize_nan_black(self) -> None:
        from pvm_labeler.common.viz import colorize_disparity

        img = colorize_disparity(np.array([[NAN, 0.0, 50.0]], np.float32), max_disp=50)
        assert tuple(img[0, 0]) == (0, 0, 0) and img[0, 2].any() and not (img[0, 1] == img[0, 2]).all()


    def test_legends_show_the_pictures_own_colours(self) -> None:
        """The disparity legend's ramp runs from colorize_disparity's colour of 0 to its colour of the top value; the
        error legend shows error_map's ten bins in order, each under its lower bound; both fit the picture's width."""
        from pvm_labeler.common.viz import (
            KITTI_ERROR_BINS,
            LEGEND_HEIGHT,
            colorize_disparity,
            disparity_legend,
            error_legend,
            with_legend,
        )

        strip = disparity_legend(300, 80.0)
        assert strip.shape == (LEGEND_HEIGHT, 300, 3) and strip.dtype == np.uint8
        ends = colorize_disparity(np.array([[0.0, 80.0]], np.float32), max_disp=80.0)[0]
        assert tuple(strip[0, 0]) == tuple(ends[0]) and tuple(strip[0, -1]) == tuple(ends[1])
        errors = error_legend(400)
        assert errors.shape == (LEGEND_HEIGHT, 400, 3)
        assert [tuple(errors[0, 20 + 40 * i]) for i in range(10)] == [rgb for _, _, rgb in KITTI_ERROR_BINS]
        assert errors[LEGEND_HEIGHT // 2:].any()  # the numbers and words are drawn
        picture = np.full((5, 300, 3), 7, np.uint8)
        both = with_legend(picture, strip)
        assert both.shape == (5 + LEGEND_HEIGHT, 300, 3) and (both[:5] == 7).all() and (both[5:] == strip).all()


    def test_a_legends_words_fit_a_narrow_picture(self) -> None:
        """On a 320 or 384 px picture (Tsukuba, the sample's scenes) the error legend's line started left of the
        strip and lost its first words: it is drawn smaller, from x = 2, and ends inside the strip."""
        from pvm_labeler.common.viz import LEGEND_HEIGHT, disparity_legend, error_legend

        for width in (320, 384, 1242):
            for strip in (error_legend(width), error_legend(width, reference="PVM/teacher"),
                          disparity_legend(width, 60.0, above=0.084)):
                words = np.nonzero(strip[28:LEGEND_HEIGHT].any(axis=(0, 2)))[0]  # the second line's columns
                assert words.size and words.min() >= 1 and words.max() <= width - 2, (width, words.min())
        # the count of values beyond the scale is drawn (the top tick reads ">=" and the line says how many)
        assert (disparity_legend(400, 60.0, above=0.084) != disparity_legend(400, 60.0)).any()


class TestReportRegions:
    def test_all_noc_occ(self, tmp_path) -> None:  # noqa: ANN001
        from pvm_labeler.report import build_report
        from pvm_labeler.shards import ShardRecord, write_shard_dir

        img = np.zeros((1, 4, 3), np.uint8)
        gt = np.array([[10.0, 20.0, 30.0, 40.0]], np.float32)
        gt_noc = np.array([[10.0, 20.0, NAN, NAN]], np.float32)  # last two pixels are occluded
        label = np.array([[11.0, NAN, 35.0, 40.5]], np.float32)
        rec = ShardRecord("f", img, img, label, label, np.ones((1, 4), np.float32), gt=gt, gt_noc=gt_noc)
        write_shard_dir(tmp_path / "s", [rec], config={"kappa1": 1.0, "kappa2": 0.1})
        result = build_report([tmp_path / "s"], tmp_path / "rep", pictures=1)
        pooled = result["runs"][0]["pooled"]
        assert pooled["all"]["density"] == 75.0 and pooled["all"]["epe"] == pytest.approx(6.5 / 3)
        assert pooled["noc"]["density"] == 50.0 and pooled["noc"]["epe"] == 1.0 and pooled["noc"]["bad3"] == 0.0
        assert pooled["occ"]["n_valid"] == 2 and pooled["occ"]["bad3"] == 50.0
        assert (tmp_path / "rep/report.md").read_text().count("| f |") == 1
        assert len(result["pictures"]) == 2  # label map + error map (a single run: no trade-off plot)

    def test_report_json_is_strict_and_report_md_shows_its_pictures(self, tmp_path) -> None:  # noqa: ANN001
        """No label on the occluded pixels: the occ region's errors are NaN, written as null (report.json held a
        bare NaN, which strict JSON readers refuse); report.md embeds the pictures it wrote beside it."""
        from pvm_labeler.report import build_report
        from pvm_labeler.shards import ShardRecord, write_shard_dir

        img = np.zeros((1, 4, 3), np.uint8)
        gt = np.array([[10.0, 20.0, 30.0, 40.0]], np.float32)
        gt_noc = np.array([[10.0, 20.0, NAN, NAN]], np.float32)
        label = np.array([[11.0, 20.0, NAN, NAN]], np.float32)
        rec = ShardRecord("f", img, img, label, label, np.ones((1, 4), np.float32), gt=gt, gt_noc=gt_noc)
        write_shard_dir(tmp_path / "s", [rec], config={"kappa1": 1.0, "kappa2": 0.1})
        result = build_report([tmp_path / "s"], tmp_path / "rep", pictures=1)
        assert math.isnan(result["runs"][0]["pooled"]["occ"]["epe"])

        def refuse(constant: str) -> None:
            raise ValueError(f"not JSON: {constant}")

        doc = json.loads((tmp_path / "rep/report.json").read_text(), parse_constant=refuse)
        assert doc["runs"][0]["pooled"]["occ"]["epe"] is None
        text = (tmp_path / "rep/report.md").read_text()
        for picture in result["pictures"]:
            rel = Path(picture).relative_to(tmp_path / "rep").as_posix()
            assert f"![{rel}]({rel})" in text and (tmp_path / "rep" / rel).is_file()

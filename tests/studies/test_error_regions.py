"""pipelines/studies/error_regions.py: the region split and the pooled table, on hand-made maps with hand-computed
counts."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.studies.error_regions import (
    EDGE_BANDS,
    REGIONS,
    add_counts,
    bad3,
    count_bad,
    count_photo_preference,
    count_reliability,
    edge_masks,
    edge_table,
    lr_consistent,
    parse_checkpoint,
    photo_errors,
    region_masks,
    reliability_table,
    table,
)

N = np.nan


def maps() -> tuple[np.ndarray, ...]:
    """A 2x4 frame: GT-valid everywhere but (1, 3); noc GT missing at (1, 2) (occluded); labels on row 0 only."""
    gt = np.array([[10, 10, 10, 10], [20, 20, 20, N]], np.float32)
    gt_noc = np.array([[10, 10, 10, 10], [20, 20, N, N]], np.float32)
    label = np.array([[10, 11, 14, N], [N, N, N, 5]], np.float32)
    return gt, gt_noc, label


def test_regions_partition_the_gt_valid_pixels() -> None:
    gt, gt_noc, label = maps()
    masks = region_masks(label, gt, gt_noc)
    assert masks["labelled"].tolist() == [[True, True, True, False], [False, False, False, False]]
    assert masks["unlabelled, noc, <= 3"].tolist() == [[False, False, False, True], [True, True, False, False]]
    assert not masks["unlabelled, noc, 3-10"].any() and not masks["unlabelled, noc, > 10"].any()
    assert masks["unlabelled, occ"].tolist() == [[False] * 4, [False, False, True, False]]
    assert sum(m.astype(int) for m in masks.values()).tolist() == np.isfinite(gt).astype(int).tolist()


def test_distance_bands() -> None:
    """One row, a label at column 0: column x is x px from it (columns 1-3, 4-10, 11-15 fall in the three bands)."""
    gt = np.full((1, 16), 5, np.float32)
    label = np.full((1, 16), N, np.float32)
    label[0, 0] = 5
    masks = region_masks(label, gt, gt)
    cols = {name: np.flatnonzero(mask[0]).tolist() for name, mask in masks.items()}
    assert cols == {"labelled": [0], "unlabelled, noc, <= 3": [1, 2, 3], "unlabelled, noc, 3-10": list(range(4, 11)),
                    "unlabelled, noc, > 10": list(range(11, 16)), "unlabelled, occ": []}


def test_without_noc_gt_nothing_is_occluded() -> None:
    gt, _, label = maps()
    assert not region_masks(label, gt, None)["unlabelled, occ"].any()


def test_counts_and_table_by_hand() -> None:
    gt, gt_noc, label = maps()
    net = np.array([[10, 14, 10, 10], [20, 30, 24, 0]], np.float32)  # bad: (0,1) 4 px, (1,1) 10 px, (1,2) 4 px
    sgm = np.array([[N, 10, 10, 10], [20, 20, 20, 20]], np.float32)  # bad: (0,0) no value
    counts = count_bad(region_masks(label, gt, gt_noc), gt, {"network": net, "sgm": sgm, "label": label})
    assert counts == {"labelled": {"n": 3, "network": 1, "sgm": 1, "label": 1},  # label 14 vs 10 is bad
                      "unlabelled, noc, <= 3": {"n": 3, "network": 1, "sgm": 0, "label": 3},
                      "unlabelled, noc, 3-10": {"n": 0, "network": 0, "sgm": 0, "label": 0},
                      "unlabelled, noc, > 10": {"n": 0, "network": 0, "sgm": 0, "label": 0},
                      "unlabelled, occ": {"n": 1, "network": 1, "sgm": 0, "label": 1}}
    total: dict = {}
    add_counts(total, counts)
    add_counts(total, counts)
    assert total["labelled"] == {"n": 6, "network": 2, "sgm": 2, "label": 2}
    rows = table(total).splitlines()
    # labelled: 6 of 14 pixels = 42.9 %, network 2/6 = 33.33 %, SGM 33.33 %, label 33.33 %, 2 of the 6 bad = 33.3 %
    assert rows[2] == "| labelled | 42.9 | 33.33 | 33.33 | 33.33 | 33.3 |"
    assert rows[4] == "| unlabelled, noc, 3-10 | 0.0 | 0.00 | 0.00 | - | 0.0 |"  # empty: no division by zero
    assert rows[6] == "| unlabelled, occ | 14.3 | 100.00 | 0.00 | - | 33.3 |"
    assert rows[7] == "| all | 100.0 | 42.86 | 14.29 | - | 100.0 |"


def test_table_reads_the_named_network() -> None:
    gt, gt_noc, label = maps()
    net = np.array([[10, 14, 10, 10], [20, 30, 24, 0]], np.float32)
    counts = count_bad(region_masks(label, gt, gt_noc), gt, {"v1": net, "v2": gt, "sgm": gt, "label": label})
    assert table(counts, "v2").splitlines()[-1] == "| all | 100.0 | 0.00 | 0.00 | - | 0.0 |"
    assert table(counts, "v1").splitlines()[-1] == "| all | 100.0 | 42.86 | 0.00 | - | 100.0 |"


def test_checkpoint_labels() -> None:
    assert parse_checkpoint("pretrained") == ("pretrained", "pretrained")
    assert parse_checkpoint("v5=out/pretrained/long_conf7") == ("v5", "out/pretrained/long_conf7")
    for bad in ("=out/run", "v5="):
        with pytest.raises(ValueError, match="LABEL=CHECKPOINT"):
            parse_checkpoint(bad)


def shifted_pair(shift: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A textured 24x48 pair with left(x) = right(x - shift): the true disparity is ``shift`` everywhere."""
    rng = np.random.default_rng(0)
    scene = rng.integers(0, 256, (24, 48 + shift, 3), dtype=np.uint8)
    return scene[:, :48].copy(), scene[:, shift:].copy()  # right(x - shift) = scene(x) = left(x)


def test_photo_errors_are_lowest_at_the_true_disparity() -> None:
    left, right = shifted_pair(4)
    true = photo_errors(left, right, np.full((24, 48), 4, np.float32))
    wrong = photo_errors(left, right, np.full((24, 48), 9, np.float32))
    assert np.isnan(true[:, :4]).all() and np.isnan(wrong[:, :9]).all()  # the warp leaves the image there
    inner = (slice(2, -2), slice(11, -2))  # away from SSIM's border and both warps' invalid columns
    assert np.nanmax(true[inner]) < 1e-3 < np.nanmin(wrong[inner])
    hole = np.full((24, 48), 4, np.float32)
    hole[5, 20] = np.nan
    assert np.isnan(photo_errors(left, right, hole)[5, 20])


def test_count_photo_preference_hand_computed() -> None:
    gt = np.array([[10, 10, 10, 10]], np.float32)
    pred = np.array([[10, 20, 20, 20]], np.float32)  # bad at columns 1-3
    err_pred = np.array([[0.1, 0.1, 0.5, N]], np.float32)  # column 3: no photometric error, not counted
    err_gt = np.array([[0.2, 0.3, 0.2, 0.2]], np.float32)
    masks = {"a": np.array([[True, True, False, False]]), "b": np.array([[False, False, True, True]])}
    got = count_photo_preference(masks, gt, pred, err_pred, err_gt)
    assert got == {"a": {"bad": 1, "prefers_pred": 1}, "b": {"bad": 1, "prefers_pred": 0}}


def test_count_reliability_hand_computed() -> None:
    gt = np.array([[10, 10, 10, 10, 10]], np.float32)
    pred = np.array([[10, 20, 10, 20, N]], np.float32)  # bad at 1, 3 and 4 (no prediction)
    reliable = np.array([[True, True, False, False, False]])
    masks = {"a": np.array([[True, True, True, True, True]])}
    assert count_reliability(masks, gt, pred, reliable) == {
        "a": {"n": 5, "reliable": 2, "bad_reliable": 1, "bad_unreliable": 2}}
    rows = {region: {"n": 0, "reliable": 0, "bad_reliable": 0, "bad_unreliable": 0} for region in REGIONS}
    rows["labelled"] = {"n": 5, "reliable": 2, "bad_reliable": 1, "bad_unreliable": 2}
    assert "| labelled | 40.0 | 50.0 | 66.7 |" in reliability_table(rows)


def test_lr_consistent_mirrors_the_right_view(monkeypatch: pytest.MonkeyPatch) -> None:
    import optstereo.api

    left, right = shifted_pair(4)
    calls = []

    def fake_predict(net: object, a: np.ndarray, b: np.ndarray, iters: int, scale: float) -> np.ndarray:
        calls.append((a, b, scale))
        out = np.full(a.shape[:2], 4, np.float32)
        out[:, -1] = 50  # the flipped pair's last column is the right view's first: mirrored back, column 0
        return out

    monkeypatch.setattr(optstereo.api, "predict", fake_predict)
    pred = np.full((24, 48), 4, np.float32)
    pred[3, 20] = 9  # disagrees with the right view (4) at column 11
    pred[5, 30] = 30  # looks up right column 0, where the right view says 50
    got = lr_consistent(object(), left, right, pred)
    np.testing.assert_array_equal(calls[0][0], right[:, ::-1])  # the flip-swapped pair: mirrored right is the new left
    np.testing.assert_array_equal(calls[0][1], left[:, ::-1])
    want = np.ones((24, 48), bool)
    want[:, :4] = False  # x - 4 < 0: the match is outside the right image
    want[:, 4] = False  # x - 4 = 0: right column 0, disparity 50 there
    want[3, 20] = want[5, 30] = False
    np.testing.assert_array_equal(got, want)
    lr_consistent(object(), left, right, pred, scale=1.125)
    assert calls[0][2] is None and calls[1][2] == 1.125  # the right view at the left prediction's input scale


def test_scaled_tables_and_flag(monkeypatch: pytest.MonkeyPatch) -> None:
    import pipelines.studies.error_regions as er

    assert er.scaled_tag("v6", 1.0) == "v6" and er.scaled_tag("v6", 1.125) == "v6 x1.125"
    seen = {}
    monkeypatch.setattr(er, "run", lambda *args: seen.update(args=args))
    er.main(["--checkpoint", "v6=pretrained", "--scale", "1", "--scale", "1.125", "--name", "s"])
    assert seen["args"] == (["v6=pretrained"], "s", False, False, (1.0, 1.125), "kitti15", False)
    er.main([])  # each file at its own input scale, named after the dataset
    assert seen["args"] == (["pretrained"], None, False, False, (None,), "kitti15", False)
    er.main(["--dataset", "kitti12", "--edges"])
    assert seen["args"][-2:] == ("kitti12", True)
    for bad in (["--scale", "0"], ["--dataset", "kitti2013"]):
        with pytest.raises(SystemExit):
            er.main(bad)


def test_run_on_another_dataset_at_the_files_input_scale(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    """run(dataset="middlebury") on the real scenes, with the matchers replaced by fakes whose errors are known: the
    regions partition each scene's GT pixels, the counts are the fakes' bad pixels, and the network runs at the input
    scale its file records when no scale is given."""
    import types

    import optstereo.api
    import pipelines.studies.error_regions as er
    import pvm_labeler.dense
    import pvm_labeler.multiscale
    from pvm_labeler.common.datasets import discover, load_pair

    if not (er.SHARED / "middlebury2001").is_dir():
        pytest.skip("../shared/data is not here")
    from optstereo.inference.config import InferenceConfig

    model = types.SimpleNamespace(inference_config=InferenceConfig(scale=1.5))
    scales = []

    def fake_predict(net, left, right, iters, scale):  # right on even columns, 5 px off on odd ones
        scales.append(scale)
        pred = np.full(left.shape[:2], 30.0, np.float32)
        pred[:, 1::2] += 5
        return pred

    def fake_label(left, right, cfg, frame_id):  # labels the top half of the frame
        label = np.full(left.shape[:2], np.nan, np.float32)
        label[: left.shape[0] // 2] = 30.0
        return types.SimpleNamespace(label=label)

    monkeypatch.setattr(optstereo.api, "load_model", lambda spec: model)
    monkeypatch.setattr(optstereo.api, "predict", fake_predict)
    monkeypatch.setattr(pvm_labeler.multiscale, "label_pair", fake_label)
    monkeypatch.setattr(pvm_labeler.dense, "sgm_left", lambda left, right, cfg, max_disp: (
        np.full(left.shape[:2], 30.0, np.float32), 0.0))
    monkeypatch.setattr(er, "RESULTS", tmp_path)
    doc = er.run(["net=pretrained"], dataset="middlebury", edges=True)
    assert scales and set(scales) == {1.5}  # the file's own input scale
    assert doc["dataset"] == "middlebury" and doc["scales"] == {"net x1.5": 1.5}
    want_n = want_net = want_sgm = want_occ = 0
    for ref in discover("middlebury", er.SHARED):
        sample = load_pair(ref)
        gt, valid = sample.gt, np.isfinite(sample.gt)
        want_n += int(valid.sum())
        if sample.gt_noc is not None:  # Motorcycle's mask0nocc; Tsukuba and Cones have none: all visible
            occ = valid & ~np.isfinite(sample.gt_noc)
            want_occ += int(occ[gt.shape[0] // 2:].sum())  # the unlabelled (bottom) half
        odd = np.zeros(gt.shape, bool)
        odd[:, 1::2] = True
        want_net += int((valid & (np.abs(np.where(odd, 35.0, 30.0) - gt) > 3)).sum())
        want_sgm += int((valid & (np.abs(30.0 - gt) > 3)).sum())
    pooled = doc["pooled"]
    assert sum(pooled[r]["n"] for r in REGIONS) == want_n  # a partition of the GT pixels
    assert sum(pooled[r]["net x1.5"] for r in REGIONS) == want_net
    assert sum(pooled[r]["sgm"] for r in REGIONS) == want_sgm
    assert pooled["unlabelled, occ"]["n"] == want_occ > 0
    assert sum(row["n"] for row in doc["edges"].values()) == want_n  # the edge bands partition them too
    assert sum(row["net x1.5"] for row in doc["edges"].values()) == want_net
    frames = doc["edge_frames"]  # per frame, and they add up to the pooled split
    assert set(frames) == {ref.frame_id for ref in discover("middlebury", er.SHARED)}
    for band, row in doc["edges"].items():
        assert row == {key: sum(counts[band][key] for counts in frames.values()) for key in row}
    assert "### middlebury2001-tsukuba, net x1.5" in (tmp_path / "middlebury.md").read_text()
    assert "## By distance to the nearest depth edge" in (tmp_path / "middlebury.md").read_text()
    assert (tmp_path / "middlebury.md").read_text().startswith("# Network errors by PVM region, Middlebury")
    with pytest.raises(ValueError, match="kitti2013"):
        er.run(["pretrained"], dataset="kitti2013")


def test_bad3_mask_is_the_ruler_of_count_bad() -> None:
    rng = np.random.default_rng(3)
    gt = rng.uniform(0, 60, (20, 30)).astype(np.float32)
    gt[rng.random(gt.shape) < 0.2] = N
    pred = (gt + rng.normal(0, 4, gt.shape)).astype(np.float32)
    pred[rng.random(gt.shape) < 0.1] = N  # holes count as bad in both
    masks = {"a": rng.random(gt.shape) < 0.5, "b": np.ones(gt.shape, bool)}
    masks = {k: m & np.isfinite(gt) for k, m in masks.items()}
    counts = count_bad(masks, gt, {"net": pred})
    for region, mask in masks.items():
        assert int((bad3(pred, gt) & mask).sum()) == counts[region]["net"]


def test_edge_masks_by_hand() -> None:
    """A 7x16 GT with a 10 px jump between columns 7 and 8, a 1 px step (no edge) between columns 3 and 4, and no GT
    at (0, 8): the edge pixels are columns 7 and 8 of rows 1-6 ((0, 7) and (0, 9) have no GT-valid neighbour across
    the jump); the bands follow the brute-force Euclidean distance to them."""
    gt = np.full((7, 16), 20.0, np.float32)
    gt[:, 4:] = 21.0  # a 1 px step: not an edge
    gt[:, 8:] = 31.0  # the jump
    gt[0, 8] = N
    masks = edge_masks(gt)
    edges = [(r, c) for r in range(1, 7) for c in (7, 8)]
    rows, cols = np.mgrid[0:7, 0:16]
    dist = np.min([np.hypot(rows - r, cols - c) for r, c in edges], axis=0)
    valid = np.isfinite(gt)
    for name, low, high in EDGE_BANDS:
        np.testing.assert_array_equal(masks[name], valid & (dist > low) & (dist <= high), err_msg=name)
    assert not masks[EDGE_BANDS[0][0]][0, 5] and masks[EDGE_BANDS[1][0]][0, 5]  # sqrt(5) from (1, 7): band 2-5
    assert sum(m.sum() for m in masks.values()) == valid.sum()  # a partition of the GT pixels
    names = [name for name, _, _ in EDGE_BANDS]
    flat = edge_masks(np.full((4, 5), 3.0, np.float32))
    assert flat[names[3]].all() and not any(flat[n].any() for n in names[:3])  # no edge at all
    none = {name: {"n": 20 if name == names[3] else 0, "net": 0, "sgm": 0} for name in names}
    assert edge_table(none, "net").startswith("No depth edge in the GT")
    some = {name: {"n": 10, "net": 5, "sgm": 1} for name in names}
    assert "| <= 2 px from a depth edge | 25.0 | 50.0 | 10.0 | 25.0 |" in edge_table(some, "net")

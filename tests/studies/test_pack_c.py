"""pipelines/studies/gpu/pack_c.py: the held-back list it excludes (the indoor validation set's pairs)."""

from __future__ import annotations

from pathlib import Path

from pipelines.studies.gpu import pack_c

REPO = Path(__file__).resolve().parents[2]


def test_names_in_skips_comments_and_blank_lines(tmp_path: Path) -> None:
    listing = tmp_path / "held.txt"
    listing.write_text("# header\n\npair_a\npair_b  # trailing note\n   \n")
    assert pack_c.names_in(listing) == {"pair_a", "pair_b"}
    assert pack_c.names_in(None) == set()


def test_the_indoor_validation_set_holds_back_ten_instereo2k_rooms() -> None:
    names = pack_c.names_in(REPO / "pipelines/studies/valset_indoor.txt")
    assert len(names) == 10 and all(n.startswith("fm_indoor_instereo2k_test_") for n in names)


def _image(path: Path, value: int) -> None:
    import cv2
    import numpy as np

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((16, 24, 3), value, np.uint8))


def test_build_encodes_the_link_packs_copies_pack_a_and_leaves_out_the_excluded(tmp_path: Path, monkeypatch) -> None:
    import numpy as np

    from pvm_labeler.common.io import read_image

    links, pack_a = tmp_path / "extra", tmp_path / "A"
    for name, value in (("fm_room_1", 40), ("fm_room_2", 120)):
        for side in ("left", "right"):
            _image(links / side / f"{name}.png", value)
    for name in ("ku_kitti_1.webp", "um_kitti_raw_1.webp"):  # um_kitti_raw is not one of pack A's prefixes
        for side in ("left", "right"):
            _image(pack_a / side / name, 200)
    monkeypatch.setattr(pack_c, "LINK_PACKS", (links,))
    monkeypatch.setattr(pack_c, "PACK_A", pack_a)
    out = tmp_path / "C"
    _image(out / "left" / "stale.webp", 0)  # from an earlier build: must not travel
    pairs, size = pack_c.build(out, 90, exclude={"fm_room_2"})
    assert pairs == 2 and sorted(p.name for p in (out / "left").iterdir()) == ["fm_room_1.webp", "ku_kitti_1.webp"]
    assert size == sum(p.stat().st_size for p in out.rglob("*.webp"))
    assert np.abs(read_image(out / "right" / "fm_room_1.webp").astype(int) - 40).max() <= 2  # flat grey survives q90
    assert (out / "left" / "ku_kitti_1.webp").read_bytes() == (pack_a / "left" / "ku_kitti_1.webp").read_bytes()

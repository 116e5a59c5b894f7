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

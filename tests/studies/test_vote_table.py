"""pipelines.studies.vote_table on two real KITTI 2015 frames (../shared/data/kitti15)."""

from __future__ import annotations

from pipelines.baselines import load_frames
from pipelines.studies.vote_table import table
from pvm_labeler.config import LabelerConfig, recipe_values

QUICK_FRAMES = ("000000", "000046")


def test_both_votes_bite_and_what_they_remove_is_worse_than_what_is_kept(shared_data):
    """The vote table on two KITTI frames: at the defaults and in the paper's recipe both hard votes reject
    pixels, and every removing stage takes away labels far worse than those it keeps (the ruler of docs/pvm.md)."""
    frames = load_frames("kitti15", shared_data / "kitti15", QUICK_FRAMES)
    # Minimum share (%) each hard vote removes alone. Measured on these two frames: defaults C1 7.1, C2 0.41
    # (15 frames: 9.6 and 1.3); paper recipe both above 10.
    bars = {"default": 0.2, "paper": 5.0}
    for name, bar in bars.items():
        cfg = LabelerConfig.from_dict(recipe_values(name))
        rows = table(frames, cfg, None)["rows"]
        summary = {g: (round(r["share"], 2), r["bad3"] and round(r["bad3"], 2)) for g, r in rows.items()}
        assert rows["C1 only"]["share"] > bar and rows["C2 only"]["share"] > bar, (name, summary)
        for group in ("C1 only", "C2 only", "LR check"):
            assert rows[group]["bad3"] > 4 * rows["kept"]["bad3"], (name, summary)

"""The CPU training pack of candidate F3 (issue 42): every unlabelled real pair, as one ``folder`` dataset of links.

The 144 pairs of ``../shared/data`` (``distill_pack.shared_sets``) plus the pairs that
``../shared/data/fetch_unlabelled_more.sh DEST MIRRORS`` copies out of public git snapshots (sections A-F; the three
single captures of section G are not fetched), with every pair whose left image is byte-identical to one already
taken dropped (the fetched drive and clips hold the every-4th frames of ``unlabelled_more``). Pairs are symbolic links
``OUT/{left,right}/<prefix>_<id>.<ext>``; the indoor table-top pairs (1280x960, 205-290 px disparities, beyond the
labeler's 192) are written halved (INTER_AREA) instead. No GT file is read. Never commit the pack.

    python -m pipelines.studies.fast_pack OUT --fetched DEST
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from pipelines.studies.gpu.distill_pack import SHARED, file_digest, halve_file, shared_sets
from pvm_labeler.common.datasets import discover

HALVED = ("indoor_rccube_lattermann",)  # fetched folders written at half size


def candidate_pairs(shared: Path, fetched: Path | None) -> list[tuple[str, Path, Path, bool]]:
    """(name stem, left, right, halve) of every pair in order: the shared sets, then each fetched folder."""
    pairs = [(f"{prefix}_{ref.frame_id}".replace("/", "_"), Path(ref.left), Path(ref.right), False)
             for prefix, reader, root, kw in shared_sets(shared) for ref in discover(reader, root, **kw)]
    for folder in sorted(p for p in (fetched.iterdir() if fetched else ()) if p.is_dir()):
        for left in sorted((folder / "image_2").iterdir()):
            pairs.append((f"fm_{folder.name}_{left.stem}", left, folder / "image_3" / left.name, folder.name in HALVED))
    return pairs


def write_pack(shared: Path, fetched: Path | None, out: Path) -> int:
    """Write the pack into ``out/left`` and ``out/right``; returns the number of pairs (duplicates dropped)."""
    for view in ("left", "right"):
        (out / view).mkdir(parents=True, exist_ok=True)
    seen: set[str] = set()
    for stem, left, right, halve in candidate_pairs(shared, fetched):
        digest = file_digest(left)
        if digest in seen:
            continue
        seen.add(digest)
        for view, src in (("left", left), ("right", right)):
            dst = out / view / f"{stem}{src.suffix}"
            if dst.exists() or dst.is_symlink():
                dst.unlink()
            if halve:
                halve_file(src, dst)
            else:
                os.symlink(src.resolve(), dst)
    return len(seen)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("out", type=Path)
    parser.add_argument("--shared", type=Path, default=SHARED)
    parser.add_argument("--fetched", type=Path, help="DEST of fetch_unlabelled_more.sh (omit: the 144 shared pairs)")
    args = parser.parse_args(argv)
    print(f"{write_pack(args.shared, args.fetched, args.out)} pairs -> {args.out}")


if __name__ == "__main__":
    main()

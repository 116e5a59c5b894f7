"""Pack C for G3's device call: the indoor and table-top pairs as WebP beside the KITTI pairs of pack A.

One folder pack (``OUT/{left,right}/<name>.webp``, the names of the link packs): every pair of ``/work/pack/extra``
(74: 50 InStereo2K rooms, 24 ZED frames) and ``/work/pack/tabletop_half`` (57 table-tops at half size) re-encoded at
WebP quality ``Q``, plus pack A's (``.carry/A``, WebP q90) 87 ``kitti_unlabelled`` pairs and its four single
``unlabelled_more`` pairs (``um_misc_*``, ``um_sid_*``), copied; ``--every N`` keeps every N-th of those. At q88: 222
pairs, 36.1 MB, which with the ~25 MB tracked tree fits the device's 64 MiB carry. ``--exclude FILE`` leaves out the
pairs named in FILE (one per line, ``#`` comments): pack D is pack C less the indoor validation set's pairs.

    python -m pipelines.studies.gpu.pack_c .carry/C --quality 88
    python -m pipelines.studies.gpu.pack_c .carry/D --quality 88 --exclude pipelines/studies/valset_indoor.txt
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from pipelines.studies.gpu.distill_pack import encode
from pvm_labeler.common.io import read_image

LINK_PACKS = (Path("/work/pack/extra"), Path("/work/pack/tabletop_half"))
PACK_A = Path(".carry/A")
A_PREFIXES = ("ku_", "um_misc", "um_sid")


def names_in(path: Path | None) -> set[str]:
    """The pair names of a list file (one per line; blank lines and ``#`` comments skipped); empty for None."""
    if path is None:
        return set()
    lines = (line.split("#", 1)[0].strip() for line in path.read_text().splitlines())
    return {line for line in lines if line}


def build(out: Path, quality: int, every: int = 1, exclude: set[str] = frozenset()) -> tuple[int, int]:
    """Write pack C (less the pairs named in ``exclude``) to ``out``, replacing what was there (a pair left from an
    earlier build would travel unseen); (pairs, bytes)."""
    shutil.rmtree(out, ignore_errors=True)
    for side in ("left", "right"):
        (out / side).mkdir(parents=True)
    total = 0
    for pack in LINK_PACKS:
        for f in sorted((pack / "left").iterdir()):
            if f.stem in exclude:
                continue
            for side in ("left", "right"):
                data = encode(read_image(pack / side / f.name), "webp", quality)
                (out / side / f"{f.stem}.webp").write_bytes(data)
                total += len(data)
    names = sorted(p.name for p in (PACK_A / "left").iterdir() if p.name.startswith(A_PREFIXES)
                   and Path(p.name).stem not in exclude)[::every]
    for name in names:
        for side in ("left", "right"):
            shutil.copy(PACK_A / side / name, out / side / name)
            total += (out / side / name).stat().st_size
    return len(list((out / "left").iterdir())), total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--quality", type=int, default=88)
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--exclude", type=Path, help="a file of pair names to leave out (held-back pairs)")
    args = parser.parse_args()
    pairs, size = build(args.out, args.quality, args.every, names_in(args.exclude))
    print(f"{pairs} pairs, {size / 1e6:.1f} MB in {args.out}")


if __name__ == "__main__":
    main()

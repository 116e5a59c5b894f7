"""Pack C for G3's device call: the indoor and table-top pairs as WebP beside the KITTI pairs of pack A.

One folder pack (``OUT/{left,right}/<name>.webp``, the names of the link packs): every pair of ``/work/pack/extra``
(74: 50 InStereo2K rooms, 24 ZED frames) and ``/work/pack/tabletop_half`` (57 table-tops at half size) re-encoded at
WebP quality ``Q``, plus pack A's (``.carry/A``, WebP q90) 87 ``kitti_unlabelled`` pairs and its four single
``unlabelled_more`` pairs (``um_misc_*``, ``um_sid_*``), copied; ``--every N`` keeps every N-th of those. At q88: 222
pairs, 36.1 MB, which with the tracked tree (~25 MB then, ~30 MB on 11-29) fits the device's 64 MiB carry.
``--exclude FILE`` leaves out the pairs named in FILE (one per line, ``#`` comments): pack D is pack C less the
indoor validation set's pairs.

    python -m pipelines.studies.gpu.pack_c .carry/C --quality 88
    python -m pipelines.studies.gpu.pack_c .carry/D --quality 88 --exclude pipelines/studies/valset_indoor.txt

``--links DIR...`` and ``--pack-a DIR`` read the link packs and pack A from elsewhere (defaults: the folders above);
``--manifest FILE`` then compares the written pack's pair names with FILE's (one per line) and fails naming the
missing and the extra ones; ``--check`` compares an existing pack without building it. Pack D from nothing but
``../shared/data`` and the fetched mirrors, in one command: ``pipelines/studies/gpu/build_pack_d.sh MIRRORS``
(its manifest: ``pipelines/studies/gpu/pack_d_manifest.txt``).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from pipelines.studies.gpu.distill_pack import encode
from pvm_labeler.common.errors import InputError
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


def pack_names(pack: Path) -> set[str]:
    """The pair names (file stems) of a folder pack; InputError when its left/ and right/ do not hold the same."""
    left, right = ({p.stem for p in (pack / side).iterdir()} if (pack / side).is_dir() else set()
                   for side in ("left", "right"))
    if left != right:
        raise InputError(f"{pack}: left/ and right/ differ: only left {sorted(left - right)}, "
                         f"only right {sorted(right - left)}")
    return left


def compare(pack: Path, manifest: Path) -> tuple[list[str], list[str]]:
    """(missing, extra): the names of ``manifest`` (``names_in``) that ``pack`` lacks, and those it has beyond them."""
    have, want = pack_names(pack), names_in(manifest)
    return sorted(want - have), sorted(have - want)


def check(pack: Path, manifest: Path) -> int:
    """The pairs of ``pack`` when its names are exactly ``manifest``'s; else InputError naming the difference."""
    missing, extra = compare(pack, manifest)
    if missing or extra:
        raise InputError(f"{pack} does not match {manifest}: {len(missing)} missing {missing}, "
                         f"{len(extra)} extra {extra}")
    return len(names_in(manifest))


def build(out: Path, quality: int, every: int = 1, exclude: set[str] = frozenset(),
          links: tuple[Path, ...] | None = None, pack_a: Path | None = None) -> tuple[int, int]:
    """Write pack C (less the pairs named in ``exclude``) to ``out``, replacing what was there (a pair left from an
    earlier build would travel unseen), from the link packs ``links`` (default ``LINK_PACKS``) and pack A's folder
    ``pack_a`` (default ``PACK_A``); (pairs, bytes)."""
    links = LINK_PACKS if links is None else links
    pack_a = PACK_A if pack_a is None else pack_a
    for folder in (*links, pack_a):
        if not (folder / "left").is_dir():
            raise InputError(f"no pack at {folder} (its left/ folder is missing)")
    shutil.rmtree(out, ignore_errors=True)
    for side in ("left", "right"):
        (out / side).mkdir(parents=True)
    total = 0
    for pack in links:
        for f in sorted((pack / "left").iterdir()):
            if f.stem in exclude:
                continue
            for side in ("left", "right"):
                data = encode(read_image(pack / side / f.name), "webp", quality)
                (out / side / f"{f.stem}.webp").write_bytes(data)
                total += len(data)
    names = sorted(p.name for p in (pack_a / "left").iterdir() if p.name.startswith(A_PREFIXES)
                   and Path(p.name).stem not in exclude)[::every]
    for name in names:
        for side in ("left", "right"):
            shutil.copy(pack_a / side / name, out / side / name)
            total += (out / side / name).stat().st_size
    return len(list((out / "left").iterdir())), total


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("out", type=Path)
    parser.add_argument("--quality", type=int, default=88)
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--exclude", type=Path, help="a file of pair names to leave out (held-back pairs)")
    parser.add_argument("--links", type=Path, nargs="+", default=list(LINK_PACKS),
                        help="the link packs re-encoded at --quality (default: %(default)s)")
    parser.add_argument("--pack-a", type=Path, default=PACK_A, help="pack A's folder (default: %(default)s)")
    parser.add_argument("--manifest", type=Path, help="fail unless the pack's pair names are exactly this file's")
    parser.add_argument("--check", action="store_true", help="only compare the existing pack OUT with --manifest")
    args = parser.parse_args(argv)
    if args.check and args.manifest is None:
        parser.error("--check needs --manifest FILE")
    try:
        if not args.check:
            pairs, size = build(args.out, args.quality, args.every, names_in(args.exclude), tuple(args.links),
                                args.pack_a)
            print(f"{pairs} pairs, {size / 1e6:.1f} MB in {args.out}")
        if args.manifest is not None:
            print(f"{check(args.out, args.manifest)} pairs in {args.out}, as {args.manifest} lists")
    except InputError as error:
        sys.exit(f"pack_c: {error}")


if __name__ == "__main__":
    main()

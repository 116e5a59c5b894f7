"""The distillation packs: every unlabelled training pair at hand as small ``folder`` datasets for a lent GPU.

Part ``shared``: kitti_unlabelled (87 pairs) and each sub-folder of unlabelled_more (57) of ../shared/data. Part
``more``: each sub-folder (``image_2`` / ``image_3``) of the folder ``fetch_unlabelled_more.sh`` fills (324 pairs),
less the pairs whose left image is byte-identical to one of part ``shared`` (57 of them). Each pair goes to
``OUT/{left,right}/<set>_<id>.<format>``; the quality is the highest of ``QUALITIES`` whose pack stays under
``--budget-mb`` (default: what the lent GPU's 64 MiB carry leaves beside the tracked tree, less 2 MB:
``carry_budget_mb``). No GT file is read or copied; a missing ``--shared`` / ``--more`` folder is named.

    python -m pipelines.studies.gpu.distill_pack .carry/A --part shared --format webp --budget-mb 37
    python -m pipelines.studies.gpu.distill_pack .carry/B --part more --more /work/unl_more --format webp --budget-mb 37

``--format link`` writes symbolic links to the original files instead (same names, lossless, no budget): the packs a
CPU run reads here, e.g. the teacher's maps of every pair (``optstereo-distill maps --root PACK``). ``--only`` /
``--skip`` keep or drop sets by folder name; ``--halve`` writes each pair at half size (lossless PNG, cv2.INTER_AREA,
names ending ``_half``): the table-top pairs, whose 205-290 px disparities are beyond the labeler's 192 at full size.

    python -m pipelines.studies.gpu.distill_pack /work/pack/more --part more --more /work/unl_more --format link \
        --skip indoor_rccube_lattermann
    python -m pipelines.studies.gpu.distill_pack /work/pack/tabletop_half --part more --more /work/unl_more \
        --only indoor_rccube_lattermann --halve
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from pvm_labeler.common.datasets import PairRef, discover
from pvm_labeler.common.errors import InputError
from pvm_labeler.common.io import read_image

SHARED = Path("../shared/data")
REPO = Path(__file__).resolve().parents[3]  # the checkout whose tracked files travel with a pack
QUALITIES = (92, 90, 88, 85, 82, 80, 75)
PARAMS = {"jpg": cv2.IMWRITE_JPEG_QUALITY, "webp": cv2.IMWRITE_WEBP_QUALITY}
SetSpec = tuple[str, str, Path, dict[str, str]]


def shared_sets(shared: Path) -> list[SetSpec]:
    """(prefix, reader, root, reader options) of every unlabelled training folder of ../shared/data."""
    sets: list[SetSpec] = [("ku", "kitti_unlabelled", shared / "kitti_unlabelled", {})]
    for folder in sorted(p for p in (shared / "unlabelled_more").iterdir() if p.is_dir()):
        sets.append((f"um_{folder.name}", "folder", folder, {"left": "image_2", "right": "image_3"}))
    return sets


def more_sets(more: Path) -> list[SetSpec]:
    """The sub-folders of the folder ``fetch_unlabelled_more.sh`` writes, as ``folder`` datasets."""
    return [(f"fm_{p.name}", "folder", p, {"left": "image_2", "right": "image_3"})
            for p in sorted(more.iterdir()) if (p / "image_2").is_dir()]


def file_digest(path: Path) -> str:
    """The MD5 of a file's bytes (byte-identical pairs are dropped by it)."""
    return hashlib.md5(path.read_bytes()).hexdigest()


def pairs(sets: list[SetSpec], exclude: set[str] = frozenset()) -> list[tuple[str, PairRef]]:
    """(prefix, pair) of every pair of ``sets`` whose left file's MD5 is not in ``exclude``."""
    return [(prefix, ref) for prefix, reader, root, kw in sets for ref in discover(reader, root, **kw)
            if not exclude or file_digest(Path(ref.left)) not in exclude]


def encode(rgb: np.ndarray, fmt: str, quality: int) -> bytes:
    """(H, W, 3) uint8 RGB -> the encoded file's bytes."""
    ok, buffer = cv2.imencode(f".{fmt}", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [PARAMS[fmt], quality])
    if not ok:
        raise InputError(f"cv2 cannot encode {fmt} at quality {quality}")
    return buffer.tobytes()


def write_pack(refs: list[tuple[str, PairRef]], out: Path, fmt: str, budget_mb: float) -> tuple[int, int, int]:
    """Encode every pair at the highest quality of ``QUALITIES`` that fits ``budget_mb``; (pairs, quality, bytes)."""
    images = [(f"{prefix}_{ref.frame_id}", read_image(ref.left), read_image(ref.right))
              for prefix, ref in tqdm(refs, desc="read", unit="pair")]
    for quality in QUALITIES:
        files = {}
        for name, left, right in tqdm(images, desc=f"{fmt} q{quality}", unit="pair"):
            files[f"left/{name}.{fmt}"] = encode(left, fmt, quality)
            files[f"right/{name}.{fmt}"] = encode(right, fmt, quality)
        size = sum(len(b) for b in files.values())
        if size <= budget_mb * 1e6:
            break
    else:
        raise InputError(f"{len(images)} pairs need {size / 1e6:.1f} MB at quality {QUALITIES[-1]}: "
                         f"over {budget_mb} MB")
    shutil.rmtree(out, ignore_errors=True)
    for rel, data in files.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(data)
    return len(images), quality, size


def select(sets: list[SetSpec], only: list[str] | None = None, skip: list[str] | None = None) -> list[SetSpec]:
    """The sets whose root folder's name is in ``only`` (all when None) and not in ``skip``."""
    return [spec for spec in sets if (only is None or spec[2].name in only) and spec[2].name not in (skip or [])]


def halve_pack(refs: list[tuple[str, PairRef]], out: Path) -> int:
    """Write ``out/{left,right}/<prefix>_<frame id>_half.png``: every pair at half size (cv2.INTER_AREA, both sides
    floored), lossless; the pairs. A pair's disparities halve with it."""
    shutil.rmtree(out, ignore_errors=True)
    for side in ("left", "right"):
        (out / side).mkdir(parents=True)
    for prefix, ref in tqdm(refs, desc="halve", unit="pair"):
        for side, path in (("left", ref.left), ("right", ref.right)):
            halve_file(Path(path), out / side / f"{prefix}_{ref.frame_id}_half.png")
    return len(refs)


def halve_file(src: Path, dst: Path) -> None:
    """Write the image ``src`` at half size (cv2.INTER_AREA, both sides floored, channels and depth as stored) to
    ``dst``, whose suffix picks the format; InputError naming the file that cannot be read or written."""
    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"cannot read image {src}")
    small = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
    if not cv2.imwrite(str(dst), small):
        raise InputError(f"cannot write {dst}")


def link_pack(refs: list[tuple[str, PairRef]], out: Path) -> int:
    """Symbolic links ``out/{left,right}/<prefix>_<frame id><suffix>`` to every pair's original files; the pairs."""
    shutil.rmtree(out, ignore_errors=True)
    for side in ("left", "right"):
        (out / side).mkdir(parents=True)
    for prefix, ref in refs:
        for side, path in (("left", Path(ref.left)), ("right", Path(ref.right))):
            (out / side / f"{prefix}_{ref.frame_id}{path.suffix.lower()}").symlink_to(path.resolve())
    return len(refs)


#: The device tool's carry (64 MiB) and the room kept free beside the tracked tree and a pack.
CARRY_BYTES, CARRY_MARGIN = 64 * 2**20, 2_000_000


def carry_budget_mb(repo: Path = REPO) -> float:
    """MB (1e6 bytes) a pack may take: the 64 MiB carry less the files git tracks in ``repo`` and a 2 MB margin."""
    listed = subprocess.run(["git", "-C", str(repo), "ls-files", "-z"], capture_output=True, check=True).stdout
    files = [repo / name.decode() for name in listed.split(b"\0") if name]
    return (CARRY_BYTES - sum(f.stat().st_size for f in files if f.is_file()) - CARRY_MARGIN) / 1e6


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("out", type=Path)
    parser.add_argument("--part", choices=("shared", "more"), default="shared")
    parser.add_argument("--shared", type=Path, default=SHARED)
    parser.add_argument("--more", type=Path, help="The folder fetch_unlabelled_more.sh filled (--part more).")
    parser.add_argument("--format", choices=(*PARAMS, "link"), default="jpg")
    parser.add_argument("--budget-mb", type=float, default=None,
                        help="Pack size in MB (default: the carry's 64 MiB less the tracked tree, less 2 MB).")
    parser.add_argument("--only", nargs="+", help="Keep only the sets of these folder names.")
    parser.add_argument("--skip", nargs="+", help="Drop the sets of these folder names.")
    parser.add_argument("--halve", action="store_true", help="Write every pair at half size (lossless PNG).")
    args = parser.parse_args(argv)
    for folder in (args.shared, args.more):
        if folder is not None and not folder.is_dir():
            parser.error(f"{folder} is not a folder (--shared: ../shared/data seen from where you run this; --more: "
                         "the folder fetch_unlabelled_more.sh filled)")
    if args.part == "shared":
        refs = pairs(select(shared_sets(args.shared), args.only, args.skip))
    else:
        if args.more is None:
            parser.error("--part more needs --more DIR")
        seen = {file_digest(Path(ref.left)) for _, ref in pairs(shared_sets(args.shared))}
        refs = pairs(select(more_sets(args.more), args.only, args.skip), exclude=seen)
    if not refs:
        raise InputError("no pair left after --only / --skip: check the folder names")
    if args.halve:
        print(f"{halve_pack(refs, args.out)} pairs -> {args.out} (half size, PNG)")
        return
    if args.format == "link":
        print(f"{link_pack(refs, args.out)} pairs -> {args.out} (links to the originals)")
        return
    budget = args.budget_mb if args.budget_mb is not None else carry_budget_mb()
    n, quality, size = write_pack(refs, args.out, args.format, budget)
    print(f"{n} pairs -> {args.out} ({args.format} q{quality}, {size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()

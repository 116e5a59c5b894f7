"""The options `pvm-label` commands share: the dataset readers' (``--left/--right/--gt/--sceneflow-pass``, on `run`,
`pack-gt` and `match`) and the labeling job's (on `run` and `pack-gt`), declared once so the commands cannot drift.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from pvm_labeler.common.datasets import DATASETS, SPLITS
from pvm_labeler.config import RECIPES, LabelerConfig
from pvm_labeler.parallel import BACKENDS
from pvm_labeler.shards import COMPRESSIONS, DEFAULT_COMPRESSION

F = TypeVar("F", bound=Callable[..., Any])

_DEFAULTS = LabelerConfig()
#: Reader option name -> ``discover`` keyword (``folder``: left/right/gt; ``sceneflow``: pass_).
READER_KEYS = {"left": "left", "right": "right", "gt": "gt", "gt_scale": "gt_scale", "sceneflow_pass": "pass_"}


def _apply(options: list[Callable[[F], F]]) -> Callable[[F], F]:
    """One decorator applying ``options`` so that ``--help`` lists them in the given order."""

    def decorate(fn: F) -> F:
        for option in reversed(options):
            fn = option(fn)
        return fn

    return decorate


def reader_options(fn: F) -> F:
    """The dataset readers' own options (``folder``: ``--left/--right/--gt/--gt-scale``; ``sceneflow``:
    ``--sceneflow-pass``)."""
    return _apply([
        click.option("--left", default=None, help="folder dataset: left images (folder or glob, relative to "
                     "--root), paired with --right by file name.  [default: left, i.e. ROOT/left]"),
        click.option("--right", default=None, help="folder dataset: right images (folder or glob, relative to "
                     "--root).  [default: right, i.e. ROOT/right]"),
        click.option("--gt", default=None, help="folder dataset: optional GT folder (KITTI-style PNG x256, .pfm or "
                     ".npy).  [default: ROOT/gt when it exists]"),
        click.option("--gt-scale", type=click.FloatRange(min=0, min_open=True), default=None,
                     help="folder dataset: integer GT PNGs hold disparity x this.  [default: 256, KITTI's]"),
        click.option("--sceneflow-pass", type=click.Choice(["clean", "final"]), default=None,
                     help="sceneflow dataset: render pass.  [default: clean]"),
    ])(fn)


def reader_option_values(values: dict[str, Any]) -> dict[str, str]:
    """``discover`` keywords from the given reader options (those left unset are left out)."""
    return {key: value if isinstance(value := values[name], float) else str(value)
            for name, key in READER_KEYS.items() if values.get(name) is not None}


def job_options(pack_gt: bool = False) -> Callable[[F], F]:
    """The labeling job's options (`run`); ``pack_gt``: `pack-gt`'s, without ``--labels`` and with the labeler's
    knobs hidden (still accepted, so `run`'s arguments and --config files work, but a GT pack runs no labeler)."""
    hide = pack_gt
    what = "Pack only the" if pack_gt else "Label only the"
    labels = [] if pack_gt else [click.option(
        "--labels", type=click.Choice(["pvm", "none"]), default="pvm", show_default=True,
        help="none = no labeling pass: shards of images + GT only (every pair needs GT), for "
             "optstereo-train --supervision gt; `pvm-label pack-gt` is the same.")]
    return _apply([
        click.option("--dataset", type=click.Choice(DATASETS), default="sample", show_default=True,
                     help="Dataset reader (official layouts; `sample` needs no files)."),
        click.option("--root", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
                     help="Dataset folder (KITTI: the folder holding training/ and testing/). Not needed for "
                          "`sample`."),
        click.option("--out", type=click.Path(path_type=Path), default=None,
                     help="Shard output directory.  [default: out/labels/DATASET]"),
        click.option("--config", "config_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
                     default=None, help="YAML file of option defaults (flag names with underscores; `labeler:` "
                     "mapping for all LabelerConfig fields). Flags override it. The resolved config is written to "
                     "OUT/config.yaml."),
        click.option("--recipe", type=click.Choice(sorted(RECIPES)), default="default", show_default=True,
                     hidden=hide, help="Starting point of the labeler config: 'paper' = the paper's PVM as written "
                     "(finest-scale label, binary votes on C1 and C2, LRDCC, nothing else); --config's labeler: and "
                     "the flags override it."),
        *labels,
        click.option("--k", type=int, default=_DEFAULTS.k, show_default=True, hidden=hide,
                     help="Pyramid scales K (>= 2)."),
        click.option("--kappa1", type=float, default=_DEFAULTS.kappa1, show_default=True, hidden=hide,
                     help="Threshold on the std of disparity across scales, px (full resolution)."),
        click.option("--kappa2", type=float, default=_DEFAULTS.kappa2, show_default=True, hidden=hide,
                     help="Threshold on the std of the normalized inverse cost across scales (unitless)."),
        click.option("--max-disp", type=int, default=_DEFAULTS.max_disp, show_default=True, hidden=hide,
                     help="Search range [0, max-disp) at full resolution, px (sample: 64 unless given)."),
        click.option("--lr-threshold", type=float, default=_DEFAULTS.lr_threshold, show_default=True, hidden=hide,
                     help="Left-right consistency threshold, px."),
        click.option("--seed", type=int, default=_DEFAULTS.seed, show_default=True, hidden=hide,
                     help="Seed of the pyramid jitter."),
        click.option("--split", type=click.Choice(SPLITS), default="training", show_default=True,
                     help="Dataset split."),
        click.option("--limit", type=click.IntRange(min=1), default=None, help=f"{what} first N pairs (sorted ids)."),
        click.option("--jobs", type=click.IntRange(min=1), default=1, show_default=True,
                     help="Parallel workers (numba threads per worker = cores // jobs)."),
        click.option("--backend", type=click.Choice(BACKENDS), default="loky", show_default=True,
                     help="loky processes, threads, or a Dask distributed cluster."),
        click.option("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786) for --backend "
                     "dask; without it a local cluster of --jobs workers is started. OUT must be on a shared file "
                     "system."),
        click.option("--shard-size", type=click.IntRange(min=1), default=2, show_default=True,
                     help="Pairs per shard (the unit of parallel work and of resume)."),
        click.option("--resume/--no-resume", default=True, show_default=True,
                     help="Skip shards that are already complete and match this config."),
        click.option("--overwrite", is_flag=True, default=False,
                     help="Delete this job's previous files in OUT first."),
        click.option("--skip-unusable", is_flag=True, default=False,
                     help="Leave out the pairs the check before labelling refuses (a missing or unreadable file, "
                          "left/right sizes that differ, an image too small for K and --max-disp), list them in "
                          "OUT/failures.json (exit 1) and label the rest; without it they stop the job before "
                          "anything is written. A re-run checks them again."),
        click.option("--quiet", is_flag=True, default=False,
                     help="No progress bar (it is also off when stderr is not a TTY)."),
        click.option("--compression", type=click.Choice(COMPRESSIONS), default=DEFAULT_COMPRESSION,
                     show_default=True, help="HDF5 compression of the shards (blosc-* need hdf5plugin, a "
                     "dependency)."),
        click.option("--numba-threads", type=click.IntRange(min=1), default=None, hidden=hide,
                     help="Numba threads per worker.  [default: cores // jobs]"),
        reader_options,
        click.option("--print-config", is_flag=True, default=False,
                     help="Print the resolved configuration (defaults + --config + flags) as YAML, the content "
                          "OUT/config.yaml would get, and exit without " + ("packing." if pack_gt else "labelling.")),
        click.option("-v", "--verbose", count=True, help="-v info, -vv debug logging on stderr."),
    ])

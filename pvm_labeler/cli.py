"""`pvm-label`: the labeling job's command line (thin: parse, build a JobSpec, call job.run).

Forms::

    pvm-label --dataset kitti15 --root data/kitti15 --out out/labels/kitti15   # same as `pvm-label run ...`
    pvm-label run --config labels.yaml --kappa1 0.8                            # YAML sets defaults, flags win
    pvm-label run --config labels.yaml --print-config                          # the resolved YAML; labels nothing
    pvm-label verify DIR                                                       # schema, counts, readability
    pvm-label report DIR [DIR ...] --out REPORT_DIR                            # label quality vs GT + pictures
    pvm-label densify DIR OUT                                                  # holes filled by superpixel planes
    pvm-label match LEFT RIGHT --out DIR --format png                          # dense SGM + fill, no network

Exit codes: 0 ok; 1 runtime failure (bad data, some pairs failed, broken shards); 2 bad usage (unknown option
values, missing --root directory, out-of-range numbers such as --k 1 or a negative kappa).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any

import click
import yaml

from pvm_labeler.common.datasets import DATASETS, DEFAULT_MAX_DISP, SPLITS
from pvm_labeler.common.errors import ConfigError, PVMError, counted
from pvm_labeler.config import RECIPES, LabelerConfig, recipe_values
from pvm_labeler.job.spec import DEFAULT_LABELER
from pvm_labeler.match import MATCH_FORMATS
from pvm_labeler.packgt import PACK_GT_LABELER
from pvm_labeler.parallel import BACKENDS
from pvm_labeler.shards import COMPRESSIONS, DEFAULT_COMPRESSION

_DEFAULTS = LabelerConfig()

#: CLI option name -> LabelerConfig field for the labeler knobs that have flags.
_LABELER_FLAGS = {"k": "k", "kappa1": "kappa1", "kappa2": "kappa2", "max_disp": "max_disp",
                  "lr_threshold": "lr_threshold", "seed": "seed"}
#: Job options that may come from --config YAML (same names as the flags, with underscores).
_JOB_KEYS = ("recipe", "labels", "dataset", "root", "out", "split", "limit", "jobs", "backend", "scheduler",
             "shard_size", "resume", "overwrite", "quiet", "compression", "numba_threads", "left", "right", "gt",
             "sceneflow_pass")


class _DefaultRunGroup(click.Group):
    """A group whose default command is ``run``, so ``pvm-label --dataset X`` works as the issue spells it."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if args and args[0] == "pack-gt":  # GT shards, no labeling pass: run with --labels none
            args = ["run", "--labels", "none", *args[1:]]
        elif not args or (args[0] not in self.commands and args[0] not in ("--help", "-h", "--version")):
            args = ["run", *args]
        return super().parse_args(ctx, args)


@click.group(cls=_DefaultRunGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="pvstereo")
def main() -> None:
    """PVM pseudo-labels for stereo datasets: label (default command `run`), `verify`, `report`, `convert`, `densify`,
    `match` (dense SGM + fill, no network);
    `pack-gt` = `run --labels none` (images + GT in shards, no labeling pass, for --supervision gt)."""


def _setup_logging(verbose: int) -> None:
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def _load_yaml(path: Path | None) -> dict[str, Any]:
    if path is None:
        return {}
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise click.BadParameter(f"cannot read YAML {path}: {exc}", param_hint="--config") from exc
    if not isinstance(doc, dict):
        raise click.BadParameter(f"{path}: expected a mapping at the top level", param_hint="--config")
    known = set(_JOB_KEYS) | set(_LABELER_FLAGS) | {"labeler", "dataset_options"}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise click.BadParameter(f"{path}: unknown keys {unknown}; known: {sorted(known)}", param_hint="--config")
    for key in ("labeler", "dataset_options"):
        if not isinstance(doc.get(key) or {}, dict):
            raise click.BadParameter(f"{path}: {key} must be a mapping, got {doc[key]!r}", param_hint="--config")
    return doc


def _merged(ctx: click.Context, yaml_doc: dict[str, Any]) -> dict[str, Any]:
    """Option values with precedence: explicit flag > --config YAML > built-in default."""
    values = {}
    for name, value in ctx.params.items():
        source = ctx.get_parameter_source(name)
        from_cli = source in (click.core.ParameterSource.COMMANDLINE, click.core.ParameterSource.ENVIRONMENT)
        values[name] = value if from_cli or name not in yaml_doc else _yaml_value(ctx, name, yaml_doc[name])
        values[f"_{name}_given"] = from_cli or name in yaml_doc
    return values


def _yaml_value(ctx: click.Context, name: str, value: Any) -> Any:
    """A --config value converted and checked by its option's click type, as the flag's would be (``jobs: many``
    is refused naming the key, not failed on later)."""
    param = next((p for p in ctx.command.params if p.name == name), None)
    if param is None or value is None or isinstance(param.type, click.types.Path):
        return value  # paths are checked where they are used (the YAML may name ones made later)
    try:
        return param.type.convert(value, param, ctx)
    except click.BadParameter as exc:
        raise click.BadParameter(f"{name}: {exc.message}", ctx=ctx, param_hint="--config") from exc


def build_spec(values: dict[str, Any], yaml_doc: dict[str, Any]) -> Any:
    """JobSpec from merged option values (exposed for tests and pipelines)."""
    from pvm_labeler.job import JobSpec

    labeler = dict(yaml_doc.get("labeler") or {})
    for flag, field_name in _LABELER_FLAGS.items():
        if values.get(f"_{flag}_given"):
            labeler[field_name] = values[flag]
    dataset = values["dataset"]
    if "max_disp" not in labeler and dataset in DEFAULT_MAX_DISP:
        labeler["max_disp"] = DEFAULT_MAX_DISP[dataset]  # e.g. sample: GT max 59.9 px, 192 would waste time
    try:
        config = LabelerConfig.from_dict({**recipe_values(values.get("recipe") or "default"), **labeler})
    except TypeError as exc:
        raise ConfigError(f"bad labeler config: {exc}") from exc
    options = dict(yaml_doc.get("dataset_options") or {})
    for key in ("left", "right", "gt"):
        if values.get(key) is not None:
            options[key] = str(values[key])
    if values.get("sceneflow_pass") is not None:
        options["pass_"] = values["sceneflow_pass"]
    label_fn = DEFAULT_LABELER
    if values.get("labels") == "none":  # recorded in the config, so resume never mixes a GT pack with labels
        label_fn = PACK_GT_LABELER
        config = LabelerConfig.from_dict({**config.to_dict(), "extra": {**config.extra, "labels": "none"}})
    root = values.get("root")
    out = values.get("out") or Path("out/labels") / dataset
    return JobSpec(
        dataset=dataset,
        root=None if root is None else Path(root),
        out=Path(out),
        config=config,
        split=values["split"],
        dataset_options=options,
        limit=values.get("limit"),
        jobs=values["jobs"],
        backend=values["backend"],
        scheduler=values.get("scheduler"),
        shard_size=values["shard_size"],
        resume=values["resume"],
        overwrite=values["overwrite"],
        quiet=values["quiet"],
        compression=values["compression"],
        numba_threads=values.get("numba_threads"),
        label_fn=label_fn,
    )


@main.command("run")
@click.option("--dataset", type=click.Choice(DATASETS), default="sample", show_default=True,
              help="Dataset reader (official layouts; `sample` needs no files).")
@click.option("--root", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="Dataset folder (KITTI: the folder holding training/ and testing/). Not needed for `sample`.")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Shard output directory.  [default: out/labels/DATASET]")
@click.option("--config", "config_file", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="YAML file of option defaults (flag names with underscores; `labeler:` mapping for all "
                   "LabelerConfig fields). Flags override it. The resolved config is written to OUT/config.yaml.")
@click.option("--recipe", type=click.Choice(sorted(RECIPES)), default="default", show_default=True,
              help="Starting point of the labeler config: 'paper' = the paper's PVM as written (finest-scale label, "
                   "binary votes on C1 and C2, LRDCC, nothing else); --config's labeler: and the flags override it.")
@click.option("--labels", type=click.Choice(["pvm", "none"]), default="pvm", show_default=True,
              help="none = no labeling pass: shards of images + GT only (every pair needs GT), for "
                   "optstereo-train --supervision gt; `pvm-label pack-gt` is the same.")
@click.option("--k", type=int, default=_DEFAULTS.k, show_default=True, help="Pyramid scales K (>= 2).")
@click.option("--kappa1", type=float, default=_DEFAULTS.kappa1, show_default=True,
              help="Threshold on the std of disparity across scales, px (full resolution).")
@click.option("--kappa2", type=float, default=_DEFAULTS.kappa2, show_default=True,
              help="Threshold on the std of the normalized inverse cost across scales (unitless).")
@click.option("--max-disp", type=int, default=_DEFAULTS.max_disp, show_default=True,
              help="Search range [0, max-disp) at full resolution, px (sample: 64 unless given).")
@click.option("--lr-threshold", type=float, default=_DEFAULTS.lr_threshold, show_default=True,
              help="Left-right consistency threshold, px.")
@click.option("--seed", type=int, default=_DEFAULTS.seed, show_default=True, help="Seed of the pyramid jitter.")
@click.option("--split", type=click.Choice(SPLITS), default="training", show_default=True, help="Dataset split.")
@click.option("--limit", type=click.IntRange(min=1), default=None, help="Label only the first N pairs (sorted ids).")
@click.option("--jobs", type=click.IntRange(min=1), default=1, show_default=True,
              help="Parallel workers (numba threads per worker = cores // jobs).")
@click.option("--backend", type=click.Choice(BACKENDS), default="loky", show_default=True,
              help="loky processes, threads, or a Dask distributed cluster.")
@click.option("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786) for --backend dask; "
              "without it a local cluster of --jobs workers is started. OUT must be on a shared file system.")
@click.option("--shard-size", type=click.IntRange(min=1), default=2, show_default=True,
              help="Pairs per shard (the unit of parallel work and of resume).")
@click.option("--resume/--no-resume", default=True, show_default=True,
              help="Skip shards that are already complete and match this config.")
@click.option("--overwrite", is_flag=True, default=False, help="Delete this job's previous files in OUT first.")
@click.option("--quiet", is_flag=True, default=False, help="No progress bar (it is also off when stderr is not a TTY).")
@click.option("--compression", type=click.Choice(COMPRESSIONS), default=DEFAULT_COMPRESSION,
              show_default=True, help="HDF5 compression of the shards (blosc-* need hdf5plugin, a dependency).")
@click.option("--numba-threads", type=click.IntRange(min=1), default=None,
              help="Numba threads per worker.  [default: cores // jobs]")
@click.option("--left", default=None, help="folder dataset: left images (folder or glob, relative to --root), "
              "paired with --right by file name.  [default: left, i.e. ROOT/left]")
@click.option("--right", default=None, help="folder dataset: right images (folder or glob, relative to --root).  "
              "[default: right, i.e. ROOT/right]")
@click.option("--gt", default=None, help="folder dataset: optional GT folder (KITTI-style PNG x256, .pfm or .npy).  "
              "[default: ROOT/gt when it exists]")
@click.option("--sceneflow-pass", type=click.Choice(["clean", "final"]), default=None,
              help="sceneflow dataset: render pass.  [default: clean]")
@click.option("--print-config", is_flag=True, default=False,
              help="Print the resolved configuration (defaults + --config + flags) as YAML, the content "
                   "OUT/config.yaml would get, and exit without labelling.")
@click.option("-v", "--verbose", count=True, help="-v info, -vv debug logging on stderr.")
@click.pass_context
def run_cmd(ctx: click.Context, config_file: Path | None, print_config: bool, verbose: int, **_: Any) -> None:
    """Label a dataset into versioned HDF5 shards (resumable; see docs/labeling.md)."""
    _setup_logging(verbose)
    from pvm_labeler.job import run

    yaml_doc = _load_yaml(config_file)
    values = _merged(ctx, yaml_doc)
    try:
        spec = build_spec(values, yaml_doc)
        if print_config:
            click.echo(yaml.safe_dump(spec.validate().resolved(), sort_keys=False), nl=False)
            return
        summary = run(spec)
    except ConfigError as exc:
        raise click.UsageError(str(exc), ctx=ctx) from exc
    except PVMError as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(summary.format())
    if summary.failures:
        ctx.exit(1)


@main.command("verify")
@click.argument("shard_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("-v", "--verbose", count=True, help="-v info logging.")
def verify_cmd(shard_dir: Path, verbose: int) -> None:
    """Check a shard directory: schema, counts, readability; names every broken shard (exit 1 if any). Pairs the
    run failed to label (failures.json) are listed; they leave the exit code 0 when the shards are sound."""
    _setup_logging(verbose)
    from pvm_labeler.job.summary import failures_lines  # lazy: the job package pulls in the labeler (numba)
    from pvm_labeler.shards import read_index, verify

    problems = verify(shard_dir)
    if problems:
        for problem in problems:
            click.echo(f"BROKEN: {problem}", err=True)
        raise click.ClickException(f"{counted(len(problems), 'problem')} in {shard_dir}")
    index = read_index(shard_dir)
    try:
        failed = failures_lines(shard_dir, index.num_samples)
    except PVMError as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(f"ok: {counted(index.num_samples, 'sample')} in {counted(len(index.shards), 'shard')}, schema "
               f"version {index.raw['schema']['version']} ({shard_dir})")
    if failed:
        click.echo("\n".join(failed))


@main.command("convert")
@click.argument("shard_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--compression", type=click.Choice(("blosc-lz4", "blosc-zstd", "lzf", "gzip", "none")), default="lzf",
              show_default=True, help="Compression of the copy (lzf and gzip need no HDF5 plugin).")
def convert_cmd(shard_dir: Path, out: Path, compression: str) -> None:
    """Rewrite SHARD_DIR into OUT with another compression (for tools that lack the Blosc plugin)."""
    from pvm_labeler.shards import convert, read_index

    try:
        convert(shard_dir, out, compression, progress=True)
    except PVMError as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(f"wrote {read_index(out).num_samples} samples into {out} ({compression})")


@main.command("densify")
@click.argument("shard_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--region-size", type=click.IntRange(min=4), default=40, show_default=True,
              help="SLIC superpixel size (px).")
@click.option("--max-rms", type=click.FloatRange(min=0, min_open=True), default=0.6, show_default=True,
              help="Largest RMS residual (px) of a superpixel's plane fit that may fill its holes.")
@click.option("--fill-confidence", type=click.FloatRange(0, 1, min_open=True), default=0.5, show_default=True,
              help="Confidence of the filled pixels (their weight in a confidence-weighted L_P).")
@click.option("--method", type=click.Choice(("planes", "sgm")), default="planes", show_default=True,
              help="planes: one plane per superpixel, both views; sgm: the left view's holes from dense SGM through "
                   "the colour-weighted median.")
@click.option("--views", type=click.Choice(("left", "both")), default="left", show_default=True,
              help="--method sgm: fill the left view's holes only, or the right view's too (writes "
                   "confidence_right, the weight of the trainer's flip-swapped samples).")
def densify_cmd(shard_dir: Path, out: Path, region_size: int, max_rms: float, fill_confidence: float,
                method: str, views: str) -> None:
    """Rewrite SHARD_DIR into OUT with label holes filled (one plane per superpixel, or filtered dense SGM)."""
    from pvm_labeler.densify import densify
    from pvm_labeler.shards import read_index

    try:
        densify(shard_dir, out, region_size, max_rms, fill_confidence, progress=True, method=method, views=views)
    except PVMError as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(f"wrote {read_index(out).num_samples} densified samples into {out}")


@main.command("match")
@click.argument("left", required=False, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("right", required=False, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: OUT/<left stem or frame id>.<format>.")
@click.option("--format", "formats", type=click.Choice(MATCH_FORMATS), multiple=True, default=("png",),
              show_default=True, help="png: KITTI 16-bit (x256, 0 = none); pfm / npy: float32, NaN = none. Repeatable.")
@click.option("--dataset", type=click.Choice(DATASETS), default=None,
              help="Match every pair of a dataset (with --root) instead of LEFT RIGHT.")
@click.option("--root", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="Dataset folder (its official layout).")
@click.option("--split", type=click.Choice(SPLITS), default="training", show_default=True, help="Dataset split.")
@click.option("--limit", type=click.IntRange(min=1), default=None, help="Only the first N pairs (sorted ids).")
@click.option("--max-disp", type=click.IntRange(min=2), default=None,
              help="Search range [0, max-disp), px.  [default: the pair's calib ndisp, else the dataset's, else "
                   f"{_DEFAULTS.max_disp}]")
@click.option("--fill/--no-fill", default=True, show_default=True,
              help="Fill SGM's holes with the nearest value on the row; --no-fill keeps them (NaN, PNG 0).")
@click.option("--jobs", type=click.IntRange(min=1), default=1, show_default=True,
              help="Pairs matched at once (numba threads per pair = cores // jobs).")
@click.option("--quiet", is_flag=True, default=False, help="No progress bar (also off when stderr is not a TTY).")
@click.option("-v", "--verbose", count=True, help="-v info logging.")
def match_cmd(left: Path | None, right: Path | None, out: Path, formats: tuple[str, ...], dataset: str | None,
              root: Path | None, split: str, limit: int | None, max_disp: int | None, fill: bool, jobs: int,
              quiet: bool, verbose: int) -> None:
    """Dense disparity fast on a CPU, no network: census SGM + row fill (pvm_labeler.dense), for LEFT RIGHT or
    --dataset NAME --root DIR."""
    _setup_logging(verbose)
    from pvm_labeler.match import match_dataset, match_pair

    if dataset is None and (left is None or right is None):
        raise click.UsageError("give LEFT RIGHT image files, or --dataset NAME (with --root)")
    if dataset is not None and left is not None:
        raise click.UsageError("give either LEFT RIGHT or --dataset, not both")
    try:
        if dataset is None:
            paths = match_pair(left, right, out, formats=formats, max_disp=max_disp, fill=fill)
            click.echo(f"wrote {', '.join(str(p) for p in paths.values())}")
            return
        done = match_dataset(dataset, root, out, split=split, formats=formats, max_disp=max_disp, fill=fill,
                             jobs=jobs, limit=limit, quiet=quiet)
    except (PVMError, OSError) as exc:  # OSError: OUT not writable (a file, no permission, disk full)
        raise click.ClickException(str(exc)) from exc
    click.echo(f"wrote {len(done)} pairs into {out} ({', '.join(formats)})")


@main.command("report")
@click.argument("shard_dirs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Report folder.  [default: FIRST_DIR/report]")
@click.option("--pictures", type=click.IntRange(min=0), default=4, show_default=True,
              help="Frames per run drawn as colour label map + error map.")
@click.option("-v", "--verbose", count=True, help="-v info logging.")
def report_cmd(shard_dirs: tuple[Path, ...], out: Path | None, pictures: int, verbose: int) -> None:
    """Label quality vs GT (density, bad-1/2/3, AEPE, noc/occ) as Markdown/JSON + PNG pictures.

    Several SHARD_DIRS (e.g. a kappa sweep) also give a density-vs-error plot.
    """
    _setup_logging(verbose)
    from pvm_labeler.report import build_report

    out = out or shard_dirs[0] / "report"
    try:
        result = build_report(list(shard_dirs), out, pictures=pictures)
    except PVMError as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(result["markdown"])
    click.echo(f"wrote {out / 'report.md'}, {out / 'report.json'} and {len(result['pictures'])} pictures")


if __name__ == "__main__":
    main()

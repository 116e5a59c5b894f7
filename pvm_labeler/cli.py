"""`pvm-label`: the labeling job's command line (thin: parse, build a JobSpec, call job.run).

Forms::

    pvm-label --dataset kitti15 --root data/kitti15 --out out/labels/kitti15   # same as `pvm-label run ...`
    pvm-label run --config labels.yaml --kappa1 0.8                            # YAML sets defaults, flags win
    pvm-label run --config labels.yaml --print-config                          # the resolved YAML; labels nothing
    pvm-label pack-gt --dataset kitti15 --root data/kitti15 --out out/gt       # images + GT shards, no labels
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

from pvm_labeler.cli_options import job_options, reader_option_values, reader_options
from pvm_labeler.common.datasets import DATASETS, DEFAULT_MAX_DISP, SPLITS
from pvm_labeler.common.errors import ConfigError, PVMError, counted
from pvm_labeler.config import LabelerConfig, recipe_values
from pvm_labeler.job.spec import DEFAULT_LABELER
from pvm_labeler.match import MATCH_FORMATS
from pvm_labeler.packgt import PACK_GT_LABELER

_DEFAULTS = LabelerConfig()

#: CLI option name -> LabelerConfig field for the labeler knobs that have flags.
_LABELER_FLAGS = {"k": "k", "kappa1": "kappa1", "kappa2": "kappa2", "max_disp": "max_disp",
                  "lr_threshold": "lr_threshold", "seed": "seed"}
#: Job options that may come from --config YAML (same names as the flags, with underscores).
_JOB_KEYS = ("recipe", "labels", "dataset", "root", "out", "split", "limit", "jobs", "backend", "scheduler",
             "shard_size", "resume", "overwrite", "quiet", "compression", "numba_threads", "left", "right", "gt",
             "gt_scale", "sceneflow_pass", "skip_unusable")


class _DefaultRunGroup(click.Group):
    """A group whose default command is ``run``, so ``pvm-label --dataset X`` works as the issue spells it."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if not args or (args[0] not in self.commands and args[0] not in ("--help", "-h", "--version")):
            args = ["run", *args]
        return super().parse_args(ctx, args)


@click.group(cls=_DefaultRunGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="pvstereo")
def main() -> None:
    """PVM pseudo-labels for stereo datasets: label (default command `run`), `verify`, `report`, `convert`, `densify`,
    `match` (dense SGM + fill, no network);
    `pack-gt` (GT-only shards: images + GT, no labeling pass, for optstereo-train --supervision gt)."""


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


#: The reader options and the one dataset that reads each (``--left`` given to ``kitti15`` would be ignored).
_READER_OWNERS = {"left": "folder", "right": "folder", "gt": "folder", "gt_scale": "folder",
                  "sceneflow_pass": "sceneflow"}


def check_dataset_options(values: dict[str, Any]) -> None:
    """ConfigError for options the chosen dataset would ignore: ``--root`` with ``sample`` (the default, built in:
    a forgotten ``--dataset`` used to label the four sample pairs and report them as a success) and a reader's
    option given to another dataset."""
    dataset = values["dataset"]
    if dataset == "sample" and values.get("root") is not None:
        raise ConfigError(f"--root {values['root']} given with the dataset `sample` (the default: built in, it "
                          "reads no files): give --dataset folder (with --left/--right) or the dataset's name "
                          "(kitti15, middlebury, ...)")
    ignored = [name for name, owner in _READER_OWNERS.items() if values.get(name) is not None and owner != dataset]
    if ignored:
        flags = ", ".join(f"--{name.replace('_', '-')}" for name in ignored)
        owners = " / ".join(sorted({_READER_OWNERS[name] for name in ignored}))
        raise ConfigError(f"{flags} {'is' if len(ignored) == 1 else 'are'} read by the {owners} dataset only, and "
                          f"--dataset is {dataset}: give --dataset {owners.split(' / ')[0]} or leave "
                          f"{'it' if len(ignored) == 1 else 'them'} out")


def build_spec(values: dict[str, Any], yaml_doc: dict[str, Any]) -> Any:
    """JobSpec from merged option values (exposed for tests and pipelines).

    Raises:
        ConfigError: options the dataset would ignore (:func:`check_dataset_options`), a bad labeler config.
    """
    from pvm_labeler.job import JobSpec

    check_dataset_options(values)
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
    options = {**(yaml_doc.get("dataset_options") or {}), **reader_option_values(values)}
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
        skip_unusable=bool(values.get("skip_unusable")),
    )


@main.command("run")
@job_options()
@click.pass_context
def run_cmd(ctx: click.Context, config_file: Path | None, print_config: bool, verbose: int, **_: Any) -> None:
    """Label a dataset into versioned HDF5 shards (resumable; see docs/labeling.md)."""
    _run_job(ctx, config_file, print_config, verbose)


@main.command("pack-gt")
@job_options(pack_gt=True)
@click.pass_context
def pack_gt_cmd(ctx: click.Context, config_file: Path | None, print_config: bool, verbose: int, **_: Any) -> None:
    """Pack a dataset's images and ground truth into versioned HDF5 shards with no labeling pass: GT-only shards
    for supervised training (optstereo-train --supervision gt). Every pair needs GT. Resumable like `run` (the same
    as `run --labels none`); the labeler's options are accepted but unused."""
    _run_job(ctx, config_file, print_config, verbose, labels="none")


def _run_job(ctx: click.Context, config_file: Path | None, print_config: bool, verbose: int,
             labels: str | None = None) -> None:
    """`run` and `pack-gt`: merge flags and --config, build the JobSpec, run it and print its summary (exit 1 when
    pairs failed). ``labels``: forced ``--labels`` value (`pack-gt`: none)."""
    _setup_logging(verbose)
    from pvm_labeler.job import run

    yaml_doc = _load_yaml(config_file)
    values = _merged(ctx, yaml_doc)
    if labels is not None:
        values["labels"] = labels
    try:
        spec = build_spec(values, yaml_doc)
        if print_config:
            click.echo(yaml.safe_dump(spec.validate().resolved(), sort_keys=False), nl=False)
            return
        summary = run(spec)
    except KeyboardInterrupt:  # Ctrl-C: shards are written whole or not at all, so a re-run resumes
        click.echo(f"interrupted: the complete shards in {spec.out} are kept; run the same command again to label "
                   "the rest (--resume is the default)", err=True)
        sys.exit(130)  # as the signal would; click's own handler said "Aborted!" and exited 1
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
@click.option("--views", type=click.Choice(("left", "both")), default=None,
              help="--method sgm: fill the left view's holes only, or the right view's too (writes "
                   "confidence_right, the weight of the trainer's flip-swapped samples).  [default: left]")
def densify_cmd(shard_dir: Path, out: Path, region_size: int, max_rms: float, fill_confidence: float,
                method: str, views: str | None) -> None:
    """Rewrite SHARD_DIR into OUT with label holes filled (one plane per superpixel, or filtered dense SGM)."""
    from pvm_labeler.densify import densify
    from pvm_labeler.shards import read_index

    if views is not None and method == "planes":  # it was ignored: planes fill both views
        raise click.UsageError(f"--views {views} is an option of --method sgm; --method planes fills both views")
    views = views or "left"

    try:
        densify(shard_dir, out, region_size, max_rms, fill_confidence, progress=True, method=method, views=views)
    except PVMError as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(f"wrote {read_index(out).num_samples} densified samples into {out}")


@main.command("match")
@click.argument("left_file", metavar="[LEFT]", required=False,
                type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("right_file", metavar="[RIGHT]", required=False,
                type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: OUT/<left stem or frame id>.<format>.")
@click.option("--format", "formats", type=click.Choice(MATCH_FORMATS), multiple=True, default=("png",),
              show_default=True, help="png: KITTI 16-bit (x256, 0 = none); pfm: float32, inf = none (Middlebury's); "
                                      "npy: float32, NaN = none. Repeatable.")
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
              help="Fill SGM's holes with the nearest value on its row; --no-fill keeps them (PNG 0, PFM inf, "
                   "NPY NaN).")
@click.option("--jobs", type=click.IntRange(min=1), default=1, show_default=True,
              help="Pairs matched at once (numba threads per pair = cores // jobs).")
@click.option("--quiet", is_flag=True, default=False, help="No progress bar (also off when stderr is not a TTY).")
@reader_options
@click.option("-v", "--verbose", count=True, help="-v info logging.")
def match_cmd(left_file: Path | None, right_file: Path | None, out: Path, formats: tuple[str, ...],
              dataset: str | None, root: Path | None, split: str, limit: int | None, max_disp: int | None, fill: bool,
              jobs: int, quiet: bool, verbose: int, **reader: str | None) -> None:
    """Dense disparity fast on a CPU, no network: census SGM + row fill (pvm_labeler.dense), for LEFT RIGHT or
    --dataset NAME --root DIR. With --dataset, a pair that cannot be read is skipped and listed in
    OUT/failures.json (exit 1 after the others are written)."""
    _setup_logging(verbose)
    from pvm_labeler.match import match_dataset, match_pair

    if dataset is None and (left_file is None or right_file is None):
        raise click.UsageError("give LEFT RIGHT image files, or --dataset NAME (with --root)")
    if dataset is not None and left_file is not None:
        raise click.UsageError("give either LEFT RIGHT or --dataset, not both")
    given = sorted(f"--{name.replace('_', '-')}" for name, value in reader.items() if value is not None)
    if dataset is None and given:
        raise click.UsageError(f"{', '.join(given)}: dataset reader options; give them with --dataset")
    try:
        if dataset is None:
            paths = match_pair(left_file, right_file, out, formats=formats, max_disp=max_disp, fill=fill)
            click.echo(f"wrote {', '.join(str(p) for p in paths.values())}")
            return
        done = match_dataset(dataset, root, out, split=split, formats=formats, max_disp=max_disp, fill=fill,
                             jobs=jobs, limit=limit, quiet=quiet, reader_options=reader_option_values(reader))
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

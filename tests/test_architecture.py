"""The layering rules of docs/architecture.md, checked by reading every module's imports (static, AST-based).

Function-local imports count, and so do imports under ``if TYPE_CHECKING:``: a rule holds for every import statement
anywhere in the file, not only at the top.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: A module longer than this has more than one job (issue: "no module of either package over ~400 lines").
MAX_MODULE_LINES = 420


#: The three packages of the tree (the product, and pipelines/studies/, which ships with none of it).
PACKAGES = ("pvm_labeler", "optstereo", "pipelines")
#: Modules of tests/ that hold no tests: the slow pure-NumPy references (and conftest.py, pytest's own).
TEST_HELPERS = ("conftest", "naive", "naive_pvm", "kernel_refs", "infer_reference")


def _modules(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported_modules(path: Path) -> set[str]:
    """Absolute names of every module ``path`` imports (``from x import y`` gives ``x`` and ``x.y``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = _module_name(path).rsplit(".", 1)[0] if path.name != "__init__.py" else _module_name(path)
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import: resolve against the importing package
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def _offenders(package: str, forbidden: tuple[str, ...], allowed: tuple[str, ...] = (),
               skip: tuple[str, ...] = (), skip_dirs: tuple[str, ...] = ()) -> dict[str, list[str]]:
    """{module: [forbidden imports]} for every module under ``package`` (files named in ``skip`` and those under the
    folders ``skip_dirs``, relative to the repository root, excepted)."""
    out = {}
    for path in _modules(package):
        if path.name in skip or any(path.is_relative_to(ROOT / d) for d in skip_dirs):
            continue
        bad = sorted(n for n in imported_modules(path)
                     if any(n == f or n.startswith(f + ".") for f in forbidden)
                     and not any(n == a or n.startswith(a + ".") for a in allowed))
        if bad:
            out[str(path.relative_to(ROOT))] = bad
    return out


def test_the_reader_sees_relative_and_local_imports(tmp_path: Path) -> None:
    pkg = ROOT / "pvm_labeler" / "common" / "datasets" / "__init__.py"
    assert "pvm_labeler.common.datasets.refs" in imported_modules(pkg)
    probe = ROOT / "pvm_labeler" / "_architecture_probe.py"
    probe.write_text("def f():\n    import torch\n    from .common import io\n")
    try:
        assert {"torch", "pvm_labeler.common", "pvm_labeler.common.io"} <= imported_modules(probe)
        assert "pvm_labeler/_architecture_probe.py" in _offenders("pvm_labeler", ("torch",))
    finally:
        probe.unlink()


def import_graph(packages: tuple[str, ...] = PACKAGES) -> dict[str, set[str]]:
    """{module: modules of ``packages`` it imports}, per import statement: ``import a.b`` points at ``a.b``;
    ``from pkg import x`` at ``pkg.x`` when that is a module (a submodule import), else at ``pkg`` (the module or
    ``__init__`` that defines the name)."""
    paths = {_module_name(p): p for pkg in packages for p in _modules(pkg)}
    graph: dict[str, set[str]] = {}
    for name, path in paths.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                subs = {f"{base}.{alias.name}" for alias in node.names} & paths.keys()
                targets.update(subs)
                if len(subs) < len(node.names):
                    targets.add(base)
        graph[name] = {n for n in targets if n in paths and n != name}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan), each sorted: the import cycles."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(cycles)


def test_the_cycle_finder_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert import_cycles(graph) == [["a", "b", "c"]]
    assert import_cycles({"a": {"b"}, "b": set()}) == []


#: Import cycles allowed: none (optstereo.checkpoint reads the version from the leaf optstereo.version).
KNOWN_CYCLES: list[list[str]] = []


def test_no_import_cycle() -> None:
    """No module of the three packages reaches itself through its imports (lazy and TYPE_CHECKING ones included)."""
    graph = import_graph()
    assert "optstereo.training.checkpoints" in graph["optstereo.training.loop"]  # the reader sees the edges it must
    assert import_cycles(graph) == KNOWN_CYCLES


#: The comment that keeps an import inside a function: ``# lazy: why`` on the statement's own line.
LAZY_MARK = "# lazy:"
#: optstereo modules that load without torch: the package itself (its API is imported lazily) and the config layer.
TORCH_FREE = ("optstereo", "optstereo.version", "optstereo.choices", "optstereo.inference.config",
              "optstereo.training.analogy_config")


def _is_type_checking(node: ast.AST) -> bool:
    test = node.test if isinstance(node, ast.If) else None
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def unmarked_local_imports(package: str = "optstereo") -> list[str]:
    """'file:line' of every import statement under ``package`` that sits inside a function or class body, outside
    ``if TYPE_CHECKING:``, and carries no ``# lazy:`` comment on its own line(s)."""
    found = []
    for path in _modules(package):
        lines = path.read_text().splitlines()

        def visit(node: ast.AST, nested: bool, path: Path = path, lines: list[str] = lines) -> None:
            for child in ast.iter_child_nodes(node):
                if _is_type_checking(child):
                    continue
                if isinstance(child, (ast.Import, ast.ImportFrom)) and nested:
                    if not any(LAZY_MARK in line for line in lines[child.lineno - 1: child.end_lineno]):
                        found.append(f"{path.relative_to(ROOT)}:{child.lineno}")
                visit(child, nested or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda,
                                                          ast.ClassDef)))

        visit(ast.parse("\n".join(lines), filename=str(path)), False)
    return found


def test_imports_sit_at_the_top_unless_marked_lazy() -> None:
    """Issue 43: imports at module level; a function-level one stays only with a ``# lazy: why`` comment (it keeps a
    torch-free module torch-free, an optional dependency optional, or numba off the commands' import path)."""
    assert unmarked_local_imports() == []
    probe = ROOT / "optstereo" / "_lazy_probe.py"
    probe.write_text("from typing import TYPE_CHECKING\n\nimport json\n\nif TYPE_CHECKING:\n    import torch\n\n\n"
                     "def f():\n    import numpy\n    from pathlib import (  # lazy: a reason\n        Path,\n    )\n"
                     "    if numpy:\n        import os\n    return json, Path, os\n\n\n"
                     "class C:\n    import re  # lazy: a reason\n")
    try:
        assert unmarked_local_imports() == ["optstereo/_lazy_probe.py:10", "optstereo/_lazy_probe.py:15"]
    finally:
        probe.unlink()


@pytest.mark.parametrize("module", TORCH_FREE)
def test_the_config_layer_loads_without_torch(module: str) -> None:
    """What the ``# lazy:`` comments of ``optstereo/__init__.py`` promise: these modules import no torch."""
    code = f"import sys, {module}; print(sorted(m for m in ('numba', 'torch') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stderr


def test_the_product_never_imports_a_study() -> None:
    """pipelines/studies/ is not installed: neither package nor any flow of pipelines/ may import it, and the two
    packages import no flow of pipelines/ either."""
    assert _offenders("pvm_labeler", ("pipelines",)) == {}
    assert _offenders("optstereo", ("pipelines",)) == {}
    assert _offenders("pipelines", ("pipelines.studies",), skip_dirs=("pipelines/studies",)) == {}


def test_the_wheel_carries_no_study() -> None:
    """`pip install .` packages what pyproject.toml's find-rule selects: the product and the flows, no study."""
    import tomllib
    from setuptools import find_packages

    rule = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    packages = find_packages(where=str(ROOT), include=rule["include"], exclude=rule.get("exclude", ()))
    assert {"pvm_labeler", "optstereo", "optstereo.training", "optstereo.cli", "pipelines"} <= set(packages)
    assert [p for p in packages if p.startswith("pipelines.studies")] == []


def test_test_modules_import_no_other_test_module() -> None:
    """What tests share lives in conftest.py (fixtures, TINY, the builders) or in helper modules holding no tests."""
    offenders = {}
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        bad = sorted(n for n in imported_modules(path)
                     if n.split(".")[-1].startswith("test_") or n.startswith("tests.test_") or n.startswith("test_"))
        if bad:
            offenders[str(path.relative_to(ROOT))] = bad
    assert offenders == {}
    helpers = {p.stem for p in (ROOT / "tests").glob("*.py") if not p.stem.startswith("test_")}
    assert helpers == set(TEST_HELPERS), "a new helper module of tests/: name it in TEST_HELPERS (it holds no tests)"


def test_only_the_shipped_weights_are_committed() -> None:
    """Candidate weights live in git history (the study JSON names the commit), not in the tree."""
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    tracked = subprocess.run(["git", "ls-files", "*.safetensors"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.split()
    assert tracked and all(Path(f).parent == Path("optstereo/weights") for f in tracked), tracked


def test_the_labeler_never_imports_torch() -> None:
    assert _offenders("pvm_labeler", ("torch", "torchvision", "optstereo")) == {}


def test_the_shared_base_imports_only_itself() -> None:
    """pvm_labeler.common is the base of both programs: nothing of the labeler proper, no numba, no torch."""
    assert _offenders("pvm_labeler/common", ("pvm_labeler", "numba", "torch", "joblib", "h5py"),
                      allowed=("pvm_labeler.common",)) == {}


def test_kernels_do_no_io() -> None:
    """Kernels take arrays and return arrays: no files, no datasets, no shards.

    ``kernels/__init__.py`` is exempt: it points numba's JIT cache at a directory keyed by the kernel sources (it
    reads the sources to hash them), which is build infrastructure, not data I/O.
    """
    io_modules = ("pvm_labeler.common", "pvm_labeler.shards", "pvm_labeler.job", "h5py", "cv2", "json", "pathlib",
                  "pickle", "yaml", "shutil", "tempfile")
    assert _offenders("pvm_labeler/kernels", io_modules, skip=("__init__.py",)) == {}
    opened = [str(p.relative_to(ROOT)) for p in _modules("pvm_labeler/kernels") if p.name != "__init__.py"
              and any(isinstance(n, ast.Call) and getattr(n.func, "id", None) == "open"
                     for n in ast.walk(ast.parse(p.read_text())))]
    assert opened == []


def test_models_know_no_training() -> None:
    training = ("optstereo.training", "optstereo.training.losses",
                "optstereo.training.analogy", "optstereo.data", "optstereo.cli", "optstereo.evaluate",
                "optstereo.distributed",
                "optstereo.checkpoint", "pvm_labeler")
    assert _offenders("optstereo/models", training, allowed=("pvm_labeler.common",)) == {}


def test_the_trainer_reaches_the_labeler_only_through_the_base_and_the_shard_schema() -> None:
    # and the disparity post-filter both programs apply (numba, so not in the base): infer's --refine, densify's fill
    assert _offenders("optstereo", ("pvm_labeler",), allowed=("pvm_labeler.common", "pvm_labeler.shards",
                                                               "pvm_labeler.refine")) == {}


def test_the_post_filter_brings_nothing_else_of_the_labeler() -> None:
    """What optstereo may import of the labeler besides the base: pvm_labeler.refine, which uses only its kernel."""
    labeler = {n for n in imported_modules(ROOT / "pvm_labeler" / "refine.py") if n.startswith("pvm_labeler")}
    assert labeler and all(n.startswith("pvm_labeler.kernels.wmedian") for n in labeler), labeler


def test_no_module_has_more_than_one_job() -> None:
    long = {str(p.relative_to(ROOT)): n for pkg in ("pvm_labeler", "optstereo") for p in _modules(pkg)
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert long == {}


@pytest.mark.parametrize("module", ["pvm_labeler.common.datasets", "pvm_labeler.common.io",
                                    "pvm_labeler.common.metrics", "pvm_labeler.shards"])
def test_the_base_and_the_schema_load_without_numba_or_torch(module: str) -> None:
    code = f"import sys, {module}; print(sorted(m for m in ('numba', 'torch') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stderr


def test_the_readme_layout_names_every_module() -> None:
    """The README's layout section matches the tree: every module and subpackage of both packages is named."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Repository layout"):]
    section = section[: section.index("\n## ", 3)]
    missing = []
    for pkg in ("pvm_labeler", "pvm_labeler/common", "optstereo"):
        for child in sorted((ROOT / pkg).iterdir()):
            name = child.name if child.is_dir() else child.stem
            is_module = child.suffix == ".py" and child.stem != "__init__"
            is_package = child.is_dir() and (child / "__init__.py").exists() and name != "common"
            if (is_module or is_package) and name not in section:
                missing.append(f"{pkg}/{child.name}")
    # optstereo's subpackages (models/, training/, cli/, data/) name each of their modules too
    missing += [str(p.relative_to(ROOT)) for p in sorted((ROOT / "optstereo").rglob("*.py"))
                if p.stem not in ("__init__", "__main__") and p.stem not in section]
    assert missing == []


def choice_list_copies(package: str = "optstereo") -> list[str]:
    """'file:line repeats choices.NAME' for every literal tuple/list/set of strings, outside optstereo/choices.py,
    that holds exactly the values of one of ``optstereo.choices``'s lists (a second home of that list)."""
    from optstereo import choices

    lists = {name: set(value) for name, value in vars(choices).items()
             if name.isupper() and isinstance(value, tuple) and len(value) > 1
             and all(isinstance(v, str) for v in value)}
    found = []
    for path in _modules(package):
        if path.name == "choices.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if not isinstance(node, (ast.Tuple, ast.List, ast.Set)) or not node.elts:
                continue
            if all(isinstance(e, ast.Constant) and isinstance(e.value, str) for e in node.elts):
                values = {e.value for e in node.elts}  # type: ignore[attr-defined]
                found += [f"{path.relative_to(ROOT)}:{node.lineno} repeats choices.{name}"
                          for name, choice in lists.items() if values == choice]
    return found


def test_each_choice_list_has_one_home() -> None:
    """Issue 43: the amp modes, devices, refiners, norms, schedules, ... are defined once (optstereo/choices.py, a
    Literal and its get_args tuple each); the configs, the CLI and inference import them."""
    assert choice_list_copies() == []
    probe = ROOT / "optstereo" / "_choices_probe.py"
    probe.write_text('AMP = ("none", "bf16", "fp16")\n')
    try:
        assert choice_list_copies() == ["optstereo/_choices_probe.py:1 repeats choices.AMP_MODES"]
    finally:
        probe.unlink()

"""The shape of the package: no import cycles, a public API in every module, tests that stand on
the package alone, and nothing that names a file outside the repository."""

import ast
import os
import re

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.join(ROOT, "cdcgs")


def package_modules() -> dict[str, str]:
    """Dotted module name -> file path, for every module of cdcgs."""
    modules = {}
    for folder, _, files in os.walk(PACKAGE):
        for name in files:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                parts = os.path.relpath(path, ROOT)[:-3].split(os.sep)
                if parts[-1] == "__init__":
                    parts = parts[:-1]
                modules[".".join(parts)] = path
    return modules


def imported_modules(module: str, path: str, modules: dict) -> set[str]:
    """The cdcgs modules that ``module`` imports anywhere in its file (functions included)."""
    is_package = path.endswith("__init__.py")
    found = set()
    for node in ast.walk(ast.parse(open(path).read())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            # `from pkg import submodule` imports the submodule; `from pkg import name` the package.
            for alias in node.names:
                candidate = f"{target}.{alias.name}"
                found.add(candidate if candidate in modules else target)
    return {name for name in found if name in modules and name != module}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for successor in graph[node]:
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return cycles


def import_graph() -> dict[str, set[str]]:
    modules = package_modules()
    return {name: imported_modules(name, path, modules) for name, path in modules.items()}


def test_the_cycle_finder_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycles(graph) == [["a", "b", "c"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_the_import_graph_sees_relative_imports():
    graph = import_graph()
    assert "cdcgs.train.ops" in graph["cdcgs.train.strategy"]  # from . import ops
    assert "cdcgs.io" in graph["cdcgs.train.outputs"]  # from ..io import load_checkpoint, ...
    assert "cdcgs.io.views" in graph["cdcgs.io.colmap"]


def test_no_import_cycles_inside_cdcgs():
    cycles = find_cycles(import_graph())
    assert not cycles, f"import cycles: {cycles}"


def test_every_public_module_declares_its_api():
    missing = []
    for name, path in package_modules().items():
        if any(part.startswith("_") and part != "__init__" for part in name.split(".")) or name.endswith("__main__"):
            continue
        tree = ast.parse(open(path).read())
        names = {
            t.id for node in tree.body if isinstance(node, ast.Assign) for t in node.targets if isinstance(t, ast.Name)
        }
        if "__all__" not in names:
            missing.append(name)
    assert not missing, f"modules without __all__: {missing}"


def test_public_names_exist():
    import importlib

    for name in package_modules():
        if name.endswith("__main__"):
            continue
        module = importlib.import_module(name)
        for exported in getattr(module, "__all__", []):
            assert hasattr(module, exported), f"{name}.__all__ names {exported!r}, which it lacks"


def python_files(*folders):
    for folder in folders:
        for base, _, files in os.walk(os.path.join(ROOT, folder)):
            yield from (os.path.join(base, f) for f in files if f.endswith(".py"))


def test_tests_import_the_package_not_each_other():
    offenders = []
    for path in python_files("tests"):
        for line in open(path):
            if re.match(r"\s*(from|import) test_\w+", line):
                offenders.append(f"{os.path.basename(path)}: {line.strip()}")
    assert not offenders, offenders


@pytest.mark.parametrize("folder", ["cdcgs", "examples"])
def test_code_names_only_files_inside_the_repository(folder):
    # A path that leaves the checkout (../shared, ../CDC-GS.md) or names this machine's folders.
    pattern = re.compile(r"\.\./[\w.-]|/work/|/root/|/home/|/tmp/")
    offenders = [
        f"{os.path.relpath(path, ROOT)}:{number}: {line.strip()}"
        for path in python_files(folder)
        for number, line in enumerate(open(path), 1)
        if pattern.search(line)
    ]
    assert not offenders, offenders


def test_no_formatter_escapes():
    marker = "fmt: " + "skip"
    offenders = [
        os.path.relpath(p, ROOT)
        for p in python_files("cdcgs", "tests", "examples", "benchmarks")
        if marker in open(p).read()
    ]
    assert not offenders, offenders


def test_the_option_reference_in_the_docs_is_current():
    import sys

    if sys.version_info[:2] != (3, 11):
        pytest.skip("argparse words its help differently across Python versions; the reference is made with 3.11")
    from cdcgs.cli import option_reference

    with open(os.path.join(ROOT, "docs", "cli.md")) as f:
        text = f.read()
    assert text.rstrip().endswith(option_reference().rstrip()), (
        "docs/cli.md's option reference is out of date: regenerate it with "
        "python -c 'from cdcgs.cli import option_reference as r; print(r())'"
    )


def test_config_imports_no_kernels_and_no_torch():
    graph = import_graph()
    reached, frontier = set(), ["cdcgs.train.config"]
    while frontier:
        module = frontier.pop()
        if module not in reached:
            reached.add(module)
            frontier.extend(graph[module])
    assert not {m for m in reached if m.startswith("cdcgs.kernels") or m == "cdcgs._interop"}, reached
    for module in reached:
        source = open(package_modules()[module]).read()
        assert not re.search(r"^\s*(import|from) (torch|warp)\b", source, re.M), module

"""The package's layers, read off the source: each imports only the layers below it.

    core            S³ algebra, the step, networks, rigid bodies, checkpoints, the state convention
    envs            Gymnasium environments over MuJoCo scenes, the scene declarations   (→ core)
    learning        data collection, the torch model, training                          (→ core, envs)
    control         export, MPC, energy shaping, the closed loop, scene → controllers   (→ core, envs)
    studies         evaluation, model quality, sweeps, reports                          (→ all of the above)
    commands        the top-level modules ``python -m fvin_mpc.<cmd>``
    benchmarks      the research studies, the repository's ``benchmarks/`` (not installed; → everything)

Imports inside functions count as much as module-level ones. torch is imported by the learning
layer (and the research studies) only: the control runtime runs without it; in the core only the
backend touches torch or CasADi. Nothing in the package imports ``benchmarks``.

Also held here: no import cycle between modules (in-function imports included: they used to hide
one), no private name (``_x``) imported from another module, no two modules with one file name, and
imports of the package's own modules at module level — inside a function only where the module
imported brings an optional heavy package (torch, CasADi, matplotlib, Ray) with it; and the package
map (``fvin_mpc/__init__.py``) names exactly the modules there are.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import pytest

import fvin_mpc

ROOT = Path(__file__).resolve().parents[1]
PACKAGE, ENVS, BENCHMARKS = ROOT / "fvin_mpc", ROOT / "envs", ROOT / "benchmarks"

ALLOWED = {
    "core": {"core"},
    "envs": {"core", "envs"},
    "learning": {"core", "envs", "learning"},
    "control": {"core", "envs", "control"},
    "studies": {"core", "envs", "learning", "control", "studies"},
    "commands": {"core", "envs", "learning", "control", "studies", "commands"},
    "benchmarks": {"core", "envs", "learning", "control", "studies", "commands", "benchmarks"},
}


def module_layer(path: Path) -> str:
    if path.is_relative_to(ENVS):
        return "envs"
    if path.is_relative_to(BENCHMARKS):
        return "benchmarks"
    parts = path.relative_to(PACKAGE).parts
    return parts[0] if len(parts) > 1 and parts[0] in ALLOWED else "commands"


def module_name(path: Path) -> str:
    """The dotted name ``path`` is imported as (``envs/`` installs as ``fvin_mpc.envs``)."""
    if path.is_relative_to(ENVS):
        parts = ("fvin_mpc", "envs", *path.relative_to(ENVS).parts)
    elif path.is_relative_to(BENCHMARKS):
        parts = ("benchmarks", *path.relative_to(BENCHMARKS).parts)
    else:  # PACKAGE, or the repository's package while a probe test points PACKAGE elsewhere
        parts = ("fvin_mpc", *path.relative_to(PACKAGE if path.is_relative_to(PACKAGE) else ROOT / "fvin_mpc").parts)
    parts = (*parts[:-1], parts[-1].removesuffix(".py"))
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, module_level_only: bool = False) -> list[tuple[str, list[str]]]:
    """``(module, names)`` of every import in ``path`` at any depth (or at module level only), relative
    imports resolved: ``import a.b`` is ``("a.b", [])``, ``from a import x, y`` is ``("a", ["x", "y"])``."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in (tree.body if module_level_only else ast.walk(tree)):
        if isinstance(node, ast.Import):
            found += [(alias.name, []) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            found.append((module, [alias.name for alias in node.names]))
    return found


def imported_modules(path: Path) -> list[str]:
    """Every absolute module name ``path`` imports (relative imports resolved), at any depth."""
    names = []
    for module, imported in imports(path):
        names.append(module)
        # ``from fvin_mpc import control`` and ``from benchmarks import paper`` import the module itself.
        names += [f"{module}.{name}" for name in imported if module in ("fvin_mpc", "fvin_mpc.studies", "benchmarks")]
    return names


def target_layer(module: str) -> str | None:
    """The layer of an imported ``fvin_mpc`` or ``benchmarks`` module, ``None`` for anything outside them."""
    parts = module.split(".")
    if parts[0] == "benchmarks":
        return "benchmarks"
    if parts[0] != "fvin_mpc" or len(parts) == 1:
        return None
    if parts[1] in ALLOWED:
        return parts[1]
    return "commands"


SOURCES = sorted([*PACKAGE.rglob("*.py"), *ENVS.rglob("*.py"), *BENCHMARKS.rglob("*.py")])
MODULES = {module_name(path): path for path in SOURCES}


def test_the_sources_are_found():
    layers = {module_layer(path) for path in SOURCES}
    assert layers == {"core", "envs", "learning", "control", "studies", "commands", "benchmarks"}


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_each_module_imports_only_the_layers_below_it(path):
    layer = module_layer(path)
    offending = [module for module in imported_modules(path)
                 if (target := target_layer(module)) is not None and target not in ALLOWED[layer]]
    assert not offending, f"{layer} module {path.name} imports {offending}"


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_torch_only_in_learning_and_backends_only_in_the_core_backend(path):
    layer = module_layer(path)
    roots = {module.split(".")[0] for module in imported_modules(path)}
    if layer not in ("learning", "benchmarks") and not path.match("fvin_mpc/core/backend.py"):
        assert "torch" not in roots, f"{path.name} imports torch"
    if layer == "core" and path.name != "backend.py":
        assert not roots & {"torch", "casadi", "gymnasium"}, f"{path.name} imports {roots}"


def test_the_layer_check_sees_an_offending_import(tmp_path, monkeypatch):
    """The check itself can fail: a core module importing the control layer is caught."""
    bad = probe_module(tmp_path, monkeypatch, "core/probe.py",
                       "def f():\n    from fvin_mpc.control.mpc import MPC\n    from ..control import scene\n")
    assert module_layer(bad) == "core"
    assert {"fvin_mpc.control.mpc", "fvin_mpc.control"} <= set(imported_modules(bad))
    with pytest.raises(AssertionError, match="imports"):
        test_each_module_imports_only_the_layers_below_it(bad)


# ---------------------------------------------------------------------- cycles, private names, file names
def import_graph(sources: dict[str, Path]) -> dict[str, set[str]]:
    """Module → the modules of ``sources`` it imports, at any depth (``from p import m`` of a module ``m``
    counts as importing ``p.m``)."""
    graph = {}
    for name, path in sources.items():
        targets = set()
        for module, imported in imports(path):
            submodules = {f"{module}.{item}" for item in imported} & sources.keys()
            targets |= submodules or ({module} & sources.keys())
        graph[name] = targets - {name}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while not component or component[-1] != node:
                component.append(stack.pop())
                on_stack.discard(component[-1])
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return cycles


def test_no_import_cycles():
    """A cycle, even one hidden in function bodies, makes import order matter and the layers a fiction."""
    assert import_cycles(import_graph(MODULES)) == []


def test_the_cycle_check_sees_a_cycle_hidden_in_a_function(tmp_path):
    (tmp_path / "a.py").write_text("import b\n")
    (tmp_path / "b.py").write_text("def f():\n    from a import x\n")
    (tmp_path / "c.py").write_text("import a\n")
    graph = {name: {module for module, _ in imports_of(tmp_path / f"{name}.py")} & {"a", "b", "c"}
             for name in ("a", "b", "c")}
    assert import_cycles(graph) == [["a", "b"]]


def imports_of(path: Path) -> list[tuple[str, list[str]]]:
    """:func:`imports` of a file outside the repository (absolute imports only)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(alias.name, []) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            found.append((node.module, [alias.name for alias in node.names]))
    return found


#: Private names imported across modules on purpose, each with why (none today).
PRIVATE_IMPORTS_ALLOWED: set[tuple[str, str, str]] = set()


def private_imports(path: Path) -> list[tuple[str, str, str]]:
    """``(importer, module, name)`` for each ``_name`` (not ``__dunder__``) ``path`` imports from another module."""
    importer = module_name(path)
    return [(importer, module, name) for module, names in imports(path) for name in names
            if name.startswith("_") and not name.startswith("__") and module != importer]


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_private_names_imported_across_modules(path):
    offending = [entry for entry in private_imports(path) if entry not in PRIVATE_IMPORTS_ALLOWED]
    assert not offending, f"{path.name} imports private names {offending}: make them public or move the code"


def probe_module(tmp_path: Path, monkeypatch, relative: str, source: str) -> Path:
    """A module ``fvin_mpc/<relative>`` of ``source`` in a package tree under ``tmp_path`` the checks read."""
    import sys

    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", tmp_path / "fvin_mpc")
    probe = tmp_path / "fvin_mpc" / relative
    probe.parent.mkdir(parents=True)
    probe.write_text(source)
    return probe


def test_the_private_name_check_sees_one(tmp_path, monkeypatch):
    probe = probe_module(tmp_path, monkeypatch, "studies/probe.py",
                         "from fvin_mpc.control.mpc import MPC, _Plan\nfrom ..core import _secret\n")
    assert private_imports(probe) == [("fvin_mpc.studies.probe", "fvin_mpc.control.mpc", "_Plan"),
                                      ("fvin_mpc.studies.probe", "fvin_mpc.core", "_secret")]


#: File names two modules share on purpose, each with why (none today).
SHARED_FILE_NAMES_ALLOWED: set[str] = set()


def test_no_two_modules_share_a_file_name():
    """``from ... import quality`` should not need its package to say which ``quality`` it means."""
    by_name: dict[str, list[str]] = {}
    for path in SOURCES:
        if path.name not in ("__init__.py", "__main__.py"):
            by_name.setdefault(path.name, []).append(str(path.relative_to(ROOT)))
    shared = {
        name: paths for name, paths in by_name.items() if len(paths) > 1 and name not in SHARED_FILE_NAMES_ALLOWED
    }
    assert not shared, f"modules that share a file name: {shared}"


#: What an in-function import may defer: packages that are optional or slow to import.
HEAVY_PACKAGES = {"torch", "casadi", "matplotlib", "ray"}
#: Files whose in-function imports of the package stay, each with why (none today).
IN_FUNCTION_IMPORTS_ALLOWED: set[str] = set()


def in_function_imports(path: Path) -> list[tuple[str, int]]:
    """``(module, line)`` of each import of the package's own modules inside a function body."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for function in ast.walk(ast.parse(path.read_text(), str(path))):
        if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(function):
            if isinstance(node, ast.ImportFrom):
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)] if node.level else []
                module = ".".join(base + ([node.module] if node.module else [])) if node.level else node.module
                modules = [f"{module}.{alias.name}" if f"{module}.{alias.name}" in MODULES else module
                           for alias in node.names]
            elif isinstance(node, ast.Import):
                modules = [alias.name for alias in node.names]
            else:
                continue
            found += [(module, node.lineno) for module in modules if module.split(".")[0] in ("fvin_mpc", "benchmarks")]
    return found


@functools.lru_cache(maxsize=None)
def brings_a_heavy_package(module: str) -> bool:
    """Whether importing ``module`` imports torch, CasADi, matplotlib or Ray (at module level,
    transitively): one search over the import graph, each module visited once."""
    stack, seen = [module], set()
    while stack:
        current = stack.pop()
        if current.split(".")[0] in HEAVY_PACKAGES:
            return True
        if current not in MODULES or current in seen:
            continue
        seen.add(current)
        stack += [f"{imported}.{name}" if f"{imported}.{name}" in MODULES else imported
                  for imported, names in imports(MODULES[current], module_level_only=True) for name in (names or [""])]
    return False


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_own_modules_are_imported_at_module_level(path):
    """An import inside a function hides what a module depends on (it hid a cycle); it stays only to
    defer an optional heavy package."""
    if path.is_relative_to(ROOT) and str(path.relative_to(ROOT)) in IN_FUNCTION_IMPORTS_ALLOWED:
        return
    deferred = [f"{module} (line {line})" for module, line in in_function_imports(path)
                if not brings_a_heavy_package(module)]
    assert not deferred, f"{path.name} imports inside functions {deferred}: import them at module level"


def test_the_in_function_check_sees_a_light_import_and_lets_a_heavy_one_be(tmp_path, monkeypatch):
    probe = probe_module(tmp_path, monkeypatch, "learning/probe.py",
                         "def f():\n    from fvin_mpc.core import s3\n"
                         "    from fvin_mpc.learning.model import model_for\n")
    assert in_function_imports(probe) == [("fvin_mpc.core.s3", 2), ("fvin_mpc.learning.model", 3)]
    with pytest.raises(AssertionError, match="fvin_mpc.core.s3"):
        test_own_modules_are_imported_at_module_level(probe)


def test_the_package_map_lists_every_module_and_no_other():
    """``fvin_mpc/__init__.py``'s docstring, the package map, names every module and none that does not exist."""
    package_map = fvin_mpc.__doc__
    modules = {path.stem for path in SOURCES if not path.is_relative_to(BENCHMARKS)} - {"__init__", "__main__"}
    listed = set(re.findall(r"^\* ``(\w+)``", package_map, re.M))
    assert sorted(modules - listed) == [], "modules the package map does not list"
    assert sorted(listed - modules) == [], "the package map lists modules that do not exist"

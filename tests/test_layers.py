"""The package's layers, read off the source: each imports only the layers below it.

    core            S³ algebra, the step, networks, rigid bodies, checkpoints, the state convention
    envs            Gymnasium environments over MuJoCo scenes, the scene declarations   (→ core)
    learning        data collection, the torch model, training                          (→ core, envs)
    control         export, MPC, energy shaping, the closed loop, scene → controllers   (→ core, envs)
    studies         evaluation, benchmarks, reports                                     (→ all of the above)
    commands        the top-level modules ``python -m fvin_mpc.<cmd>`` (and fvin_mpc.bench)

Imports inside functions count as much as module-level ones. torch is imported by the learning
layer only (the control runtime runs without it); in the core only the backend touches torch or
CasADi.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE, ENVS = ROOT / "fvin_mpc", ROOT / "envs"

ALLOWED = {
    "core": {"core"},
    "envs": {"core", "envs"},
    "learning": {"core", "envs", "learning"},
    "control": {"core", "envs", "control"},
    "studies": {"core", "envs", "learning", "control", "studies"},
}


def module_layer(path: Path) -> str:
    if path.is_relative_to(ENVS):
        return "envs"
    parts = path.relative_to(PACKAGE).parts
    return parts[0] if len(parts) > 1 and parts[0] in ALLOWED else "commands"


def imported_modules(path: Path) -> list[str]:
    """Every absolute module name ``path`` imports (relative imports resolved), at any depth."""
    package = ("fvin_mpc.envs" if path.is_relative_to(ENVS)
               else ".".join(("fvin_mpc", *path.relative_to(PACKAGE).parent.parts)).rstrip("."))
    names = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            names.append(module)
            # ``from fvin_mpc import control`` imports the subpackage itself.
            names += [f"{module}.{alias.name}" for alias in node.names if module in ("fvin_mpc", "fvin_mpc.studies")]
    return names


def target_layer(module: str) -> str | None:
    """The layer of an imported ``fvin_mpc`` module, ``None`` for anything outside the package."""
    parts = module.split(".")
    if parts[0] != "fvin_mpc" or len(parts) == 1:
        return None
    if parts[1] in ALLOWED:
        return parts[1]
    return "commands"


SOURCES = sorted([*PACKAGE.rglob("*.py"), *ENVS.rglob("*.py")])


def test_the_sources_are_found():
    layers = {module_layer(path) for path in SOURCES}
    assert layers == {"core", "envs", "learning", "control", "studies", "commands"}


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_each_module_imports_only_the_layers_below_it(path):
    layer = module_layer(path)
    if layer == "commands":
        return
    offending = [module for module in imported_modules(path)
                 if (target := target_layer(module)) is not None and target not in ALLOWED[layer]]
    assert not offending, f"{layer} module {path.name} imports {offending}"


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_torch_only_in_learning_and_backends_only_in_the_core_backend(path):
    layer = module_layer(path)
    roots = {module.split(".")[0] for module in imported_modules(path)}
    if layer != "learning" and not path.match("fvin_mpc/core/backend.py"):
        assert "torch" not in roots, f"{path.name} imports torch"
    if layer == "core" and path.name != "backend.py":
        assert not roots & {"torch", "casadi", "gymnasium"}, f"{path.name} imports {roots}"


def test_the_layer_check_sees_an_offending_import(tmp_path, monkeypatch):
    """The check itself can fail: a core module importing the control layer is caught."""
    import sys

    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", tmp_path / "fvin_mpc")
    bad = tmp_path / "fvin_mpc" / "core" / "probe.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("def f():\n    from fvin_mpc.control.mpc import MPC\n    from ..control import scene\n")
    assert module_layer(bad) == "core"
    assert {"fvin_mpc.control.mpc", "fvin_mpc.control"} <= set(imported_modules(bad))
    with pytest.raises(AssertionError, match="imports"):
        test_each_module_imports_only_the_layers_below_it(bad)

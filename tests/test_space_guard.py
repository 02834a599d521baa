"""The configuration space is told one way: by the value code carries (:mod:`fvin_mpc.core.space`).

This test reads the package's source and fails where code outside the registry tells a space another
way — by the class of a model config (``isinstance(config, R3S3Config)``), by comparing a space's
name (``checkpoint.configuration_space == "R3xS3"``, ``space == "S3"``) or by a state's length
(``len(x) == 13``, ``STATE_DIM``, ``layout_of(n)``). Code that needs to know asks the space
(``space.layout`` and its blocks, ``space.step``, ``model.require(...)``).

It also fails where code assumes a state holds one quaternion: a literal state slice (``x[:4]``,
``x[4:7]``, ``x[3:7]``), a symbol of a literal state size (``SX.sym("x", 7)``), ``ns - 3`` for ``ω``, the
one-quaternion layout's fields (``layout.quaternion``, ``layout.omega``, ``layout.before``, …) and
``.pivoted`` (what the goal is belongs to the scene: its ``goal_set``). A state is a product of blocks
(:mod:`fvin_mpc.core.blocks`); code reads it through the layout's slots, or through
``layout.attitude(by=...)`` where it is written for one body.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Any

import pytest

from fvin_mpc.core.space import spaces

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted([*(ROOT / "fvin_mpc").rglob("*.py"), *(ROOT / "envs").rglob("*.py")])
#: The registry itself may say everything about spaces.
REGISTRY = ROOT / "fvin_mpc" / "core" / "space.py"
#: A space's own step module may check the length of its own states (and only that).
STEP_MODULES = {ROOT / "fvin_mpc" / "core" / name for name in ("fvin.py", "fvin_so3.py", "fvin_r3s3.py")}

CONFIG_CLASSES = {space.config_type.__name__ for space in spaces()}
SPACE_NAMES = {space.name for space in spaces()}
STATE_SIZES = {space.state_dim for space in spaces()}
#: Names that encode a state length or pick a layout by one.
LENGTH_NAMES = {"STATE_DIM", "FREE_STATE_DIM", "layout_of"}
#: The blocks themselves, and the modules that define a space's own states (its step and closed form), may slice
#: states by position.
STATE_MODULES = STEP_MODULES | {ROOT / "fvin_mpc" / "core" / name for name in ("blocks.py", "quadrotor.py",
                                                                                "rigid_body.py")}
#: Slice bounds that cut a single body's state where one quaternion sits: ``[:4]``, ``[4:7]``, ``[3:7]``, …
STATE_CUTS = {(None, 4), (0, 4), (4, None), (4, 7), (3, 7), (7, 10), (7, 13), (10, 13), (10, None), (7, None)}
#: Fields of the one-quaternion layout (``R^a × S³ × R^b``) that the product of blocks replaced.
ONE_QUATERNION_FIELDS = {"quaternion", "omega", "chart", "tangent_omega", "before", "after"}


def _name(node: ast.AST) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def _is_length_probe(node: ast.AST) -> bool:
    """``len(...)``, ``….shape[...]``, ``….size1_in(...)``, ``….state_dim``: something a state's length is read from."""
    if isinstance(node, ast.Call) and _name(node.func) in ("len", "size1_in", "size1"):
        return True
    if isinstance(node, ast.Subscript) and _name(node.value) == "shape":
        return True
    return _name(node) in ("state_dim", "size")


def _constant(node: ast.AST | None) -> Any:
    return node.value if isinstance(node, ast.Constant) else None


def _state_cuts(node: ast.Subscript) -> list[str]:
    """The slices of ``node`` whose constant bounds are one of :data:`STATE_CUTS`."""
    parts = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
    cuts = []
    for part in parts:
        if isinstance(part, ast.Slice) and part.step is None and (part.lower is None or _constant(part.lower)) \
                and (part.upper is None or _constant(part.upper)):
            bounds = (_constant(part.lower), _constant(part.upper))
            if bounds in STATE_CUTS:
                cuts.append(ast.unparse(part))
    return cuts


def _names_a_layout(node: ast.AST) -> bool:
    name = _name(node)
    return name is not None and name.lower().endswith("layout") or \
        isinstance(node, ast.Attribute) and _name(node.value) in ("space",) and node.attr == "layout"


def violations(path: Path, root: Path = ROOT) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        where = f"{path.relative_to(root)}:{getattr(node, 'lineno', '?')}"
        if isinstance(node, ast.Attribute) and node.attr == "pivoted":
            found.append(f"{where}: .pivoted (the goal's kind is the scene's: its goal_set)")
        if isinstance(node, ast.Attribute) and node.attr in ONE_QUATERNION_FIELDS and _names_a_layout(node.value):
            found.append(f"{where}: a layout's .{node.attr} assumes one quaternion (read a block's slots, "
                         "or layout.attitude(by=...))")
        if isinstance(node, ast.Subscript) and path not in STATE_MODULES:
            for cut in _state_cuts(node):
                found.append(f"{where}: a literal state slice [{cut}] (read the layout's slots)")
        if isinstance(node, ast.Call) and _name(node.func) == "sym" and len(node.args) >= 2 \
                and _constant(node.args[1]) in STATE_SIZES and path not in STATE_MODULES:
            found.append(f"{where}: a symbol of a literal state size {_constant(node.args[1])}")
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Sub) and _constant(node.right) == 3 \
                and _name(node.left) in ("ns", "n", "state_dim", "nx"):
            found.append(f"{where}: {ast.unparse(node)} (ω as a state's last three entries)")
        if isinstance(node, ast.Call) and _name(node.func) == "StateLayout" \
                and {k.arg for k in node.keywords} & {"before", "after"}:
            found.append(f"{where}: StateLayout(before=…, after=…) (a layout is a product of blocks)")
        if isinstance(node, ast.Call) and _name(node.func) == "isinstance" and len(node.args) == 2:
            classes = node.args[1].elts if isinstance(node.args[1], ast.Tuple) else [node.args[1]]
            hit = CONFIG_CLASSES & {_name(c) for c in classes}
            if hit:
                found.append(f"{where}: isinstance on a space's config class {sorted(hit)}")
        if isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            strings = {o.value for o in operands if isinstance(o, ast.Constant) and isinstance(o.value, str)}
            for container in operands:  # x in ("S3", "SO3")
                if isinstance(container, (ast.Tuple, ast.List, ast.Set)):
                    strings |= {
                        e.value for e in container.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)
                    }
            if strings & SPACE_NAMES:
                found.append(f"{where}: compares with a space's name {sorted(strings & SPACE_NAMES)}")
            if any(_name(o) in ("configuration_space", "CONFIGURATION_SPACE") for o in operands):
                found.append(f"{where}: compares a configuration_space")
            sizes = {o.value for o in operands if isinstance(o, ast.Constant) and isinstance(o.value, int)}
            if sizes & STATE_SIZES and any(_is_length_probe(o) for o in operands) and path not in STEP_MODULES:
                found.append(f"{where}: tells a space by a state length {sorted(sizes & STATE_SIZES)}")
        if isinstance(node, (ast.Name, ast.Attribute)) and _name(node) in LENGTH_NAMES and path not in STEP_MODULES:
            found.append(f"{where}: {_name(node)} (a state length standing for a space)")
        if isinstance(node, ast.alias) and node.name in LENGTH_NAMES and path not in STEP_MODULES:
            found.append(f"{where}: imports {node.name}")
    return found


def test_the_guard_sees_what_it_forbids(tmp_path):
    """Each forbidden form, written into a scratch module, is reported (the guard can fail)."""
    bad = tmp_path / "bad.py"
    bad.write_text(
        "from fvin_mpc.core.networks_r3s3 import R3S3Config\n"
        "def f(config, checkpoint, x, space):\n"
        "    a = isinstance(config, R3S3Config)\n"
        "    b = checkpoint.configuration_space == 'R3xS3'\n"
        "    c = space in ('S3', 'SO3')\n"
        "    d = len(x) == 13\n"
        "    e = x.shape[-1] != 7\n"
        "    return STATE_DIM\n"
    )
    found = violations(bad, root=tmp_path)
    assert {int(line.split(":")[1]) for line in found} == {3, 4, 5, 6, 7, 8}, found
    for fragment in ("isinstance", "configuration_space", "space's name", "state length [13]", "state length [7]",
                     "STATE_DIM"):
        assert any(fragment in line for line in found), (fragment, found)


def test_the_guard_sees_one_quaternion_assumptions(tmp_path):
    """Each one-quaternion form, written into a scratch module, is reported; the block-wise forms are not."""
    bad = tmp_path / "one_body.py"
    bad.write_text(
        "import casadi as ca\n"
        "from fvin_mpc.core.space import StateLayout\n"
        "def f(x, layout, space, ns, model, base):\n"
        "    q, w = x[:4], x[4:7]\n"
        "    v = x[..., 3:7]\n"
        "    s = ca.SX.sym('x', 7)\n"
        "    o = ns - 3\n"
        "    a = layout.quaternion\n"
        "    b = space.layout.omega\n"
        "    c = model.space.pivoted\n"
        "    d = StateLayout(before=1, after=4, name='(s, q, ṡ, ω)')\n"
        "    fine = x[layout.attitude(by='f').quaternion], x[layout.rates], x[:3], layout.slots[0].position\n"
        "    return base.spec.goal_set.attitude_at_rest\n"
    )
    found = violations(bad, root=tmp_path)
    assert sorted({int(line.split(":")[1]) for line in found}) == [4, 5, 6, 7, 8, 9, 10, 11], found
    for fragment in ("[:4]", "[4:7]", "[3:7]", "literal state size 7", "ns - 3", ".quaternion", ".omega", ".pivoted",
                     "before=…"):
        assert any(fragment in line for line in found), (fragment, found)


@pytest.mark.parametrize("path", [p for p in SOURCES if p != REGISTRY], ids=lambda p: str(p.relative_to(ROOT)))
def test_no_code_outside_the_registry_tells_a_space_another_way(path):
    assert violations(path) == []

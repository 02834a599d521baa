"""A seeded random family of mechanisms — trees of 2 to 4 joints (hinge, slide, ball) — as MJCF.

``mechanism_scene(kind, seed)`` returns ``(mjcf_text, facts)``: a self-contained MJCF and the drawn
parameters; ``mechanism_mjcf(kind, seed)`` the text alone. Everything comes from
``numpy.random.default_rng([seed, KINDS.index(kind)])``, so a ``(kind, seed)`` is a mechanism, and
:data:`MEMBERS` lists the members the closed-form check (``tests/test_tree_dynamics.py``,
``benchmarks/tree_dynamics_check.py``) runs on: seeds 0, 1, 2 of every kind. :func:`random_joint_states`,
:func:`mujoco_terms` and :func:`closed_form_errors` are that check's states, its oracle and its measure.

The kinds (:data:`KINDS`):

* ``cart_pole`` — a cart on a rail (slide; a horizontal direction drawn at random; a travel limit in half the
  draws) carrying 1–3 poles on hinges (axes across the rail, each tilted up to 15°); the cart pushed by a
  joint motor or by a site's force along the rail, and in a quarter of the draws the first pole driven too;
* ``double_pendulum`` — 2 or 3 links on hinges about one horizontal axis (in 30 % of the draws the later axes
  tilted up to 30°: not planar), driven at the shoulder (pendubot), the elbow (acrobot) or every joint (by
  ``seed % 3``, in that order, so that any three consecutive seeds hold all three);
* ``furuta`` — a rotary pendulum: an arm on a hinge about the vertical (tilted up to 10°) and a pendulum on
  a hinge about the arm's long axis (a second pendulum link below it in 30 % of the draws); the arm driven
  by a joint motor or by a site's torque about its axis;
* ``ball_arm`` — a two-link arm on a ball joint at the shoulder, and at the elbow a hinge (across the upper
  arm), a ball, or a hinge and a second hinge at a wrist; the shoulder driven by 2–3 motors through a joint
  or jointinparent transmission with random gear directions, or by sites' torques; the elbow hinge by a
  motor in 70 % of the draws (the elbow's kind and the shoulder's transmission by ``seed % 3``, in those
  orders).

In every draw: link lengths 0.2–1 m, masses 0.05–2 kg (log-uniform; a cart 0.2–3 kg); each link's inertia
from a capsule geom (half the draws) or an explicit ``<inertial>`` with a random centre of mass and a random
full inertia (principal moments of a random box, turned at random); damping none or 1e-3–0.5 and armature
none or 1e-4–0.05 per joint (log-uniform, half the draws each); a spring on a hinge or slide in a fifth of
them, and a hinge's ``ref`` (its ``qpos0``) random in a fifth; every body's frame turned at random in half
the draws (the mechanism is the same, its numbers in the MJCF are not); every actuator a ``motor`` with
``ctrlrange`` ±1 and gear ±(0.2–50), log-uniform;
gravity 1.6–9.81 m/s² along −z; timestep 2–10 ms; integrator Euler, RK4 or implicitfast. Contacts are
disabled (``<flag contact="disable"/>``) and the energy is on (``energy="enable"``: MuJoCo's potential and
kinetic energy, which the tests read).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.tree_dynamics import KinematicTree

KINDS = ("cart_pole", "double_pendulum", "furuta", "ball_arm")
#: The members the closed-form check runs on, in order: seeds 0, 1, 2 of every kind.
MEMBERS: tuple[tuple[str, int], ...] = tuple((kind, seed) for kind in KINDS for seed in range(3))

_DOWN = np.array([0.0, 0.0, -1.0])
NP_OPS = get_ops("numpy")


# ----------------------------------------------------------------------------- draws
def _log_draw(rng: np.random.Generator, low: float, high: float) -> float:
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


def _maybe(rng: np.random.Generator, chance: float, low: float, high: float) -> float:
    """Zero, or (with ``chance``) a log-uniform draw in ``[low, high]``."""
    return _log_draw(rng, low, high) if rng.uniform() < chance else 0.0


def _gear(rng: np.random.Generator) -> float:
    return float(rng.choice([-1.0, 1.0])) * _log_draw(rng, 0.2, 50.0)


def _turn(axis: np.ndarray, angle: float) -> np.ndarray:
    """The rotation matrix by ``angle`` about unit ``axis``."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def _uniform_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    matrix = np.zeros(9)
    mujoco.mju_quat2Mat(matrix, q / np.linalg.norm(q))
    return matrix.reshape(3, 3)


def _tilted(rng: np.random.Generator, axis: np.ndarray, max_deg: float) -> np.ndarray:
    """``axis`` turned by up to ``max_deg`` about a random direction across it."""
    across = np.cross(axis, rng.normal(size=3))
    return _turn(across / np.linalg.norm(across), math.radians(rng.uniform(0.0, max_deg))) @ axis


def _across(axis: np.ndarray, helper: np.ndarray) -> np.ndarray:
    v = np.cross(axis, helper)
    return v / np.linalg.norm(v)


# ----------------------------------------------------------------------------- a mechanism, in the world at qpos0
@dataclass
class _Joint:
    name: str
    kind: str
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    attributes: dict[str, float] = field(default_factory=dict)
    limit: tuple[float, float] | None = None


@dataclass
class _Link:
    """A body: its origin and frame in the world at ``qpos0``, joints at its origin, and what it carries
    (world coordinates; written into its own frame by :func:`_write`)."""

    name: str
    origin: np.ndarray
    frame: np.ndarray
    joints: list[_Joint]
    mass: float
    tip: np.ndarray
    inertial: dict[str, Any] | None = None
    sites: dict[str, np.ndarray] = field(default_factory=dict)
    children: list["_Link"] = field(default_factory=list)


def _joint(rng: np.random.Generator, name: str, kind: str, axis: np.ndarray | None = None) -> _Joint:
    attributes = {"damping": _maybe(rng, 0.5, 1e-3, 0.5), "armature": _maybe(rng, 0.5, 1e-4, 0.05)}
    if kind in ("hinge", "slide") and rng.uniform() < 0.2:
        attributes["stiffness"] = _log_draw(rng, 0.05, 5.0)
        attributes["springref"] = float(rng.uniform(-0.5, 0.5))
    if kind == "hinge" and rng.uniform() < 0.2:
        attributes["ref"] = float(rng.uniform(-math.pi, math.pi))
    return _Joint(name, kind, np.array([0.0, 0.0, 1.0]) if axis is None else axis / np.linalg.norm(axis),
                  {k: v for k, v in attributes.items() if v != 0.0})


def _link(rng: np.random.Generator, name: str, origin: np.ndarray, direction: np.ndarray, joints: list[_Joint],
          mass: float | None = None, length: float | None = None) -> _Link:
    """A link from ``origin`` along unit ``direction``: its mass, length and inertia drawn."""
    length = float(rng.uniform(0.2, 1.0)) if length is None else length
    mass = _log_draw(rng, 0.05, 2.0) if mass is None else mass
    frame = _uniform_rotation(rng) if rng.uniform() < 0.5 else np.eye(3)
    link = _Link(name, origin, frame, joints, mass, origin + length * direction)
    if rng.uniform() < 0.5:  # an explicit inertial: random centre of mass and full inertia
        offset = float(rng.uniform(0.3, 1.0)) * length * direction + 0.05 * length * rng.normal(size=3)
        box = rng.uniform(0.02, 1.0, size=3) * length
        squares = box * box
        principal = mass / 12.0 * (squares.sum() - squares)  # a box's: (b² + c², a² + c², a² + b²)/12
        turn = _uniform_rotation(rng)
        link.inertial = {"center": origin + offset, "inertia": turn @ np.diag(principal) @ turn.T}
    return link


def _place(link: _Link, parent_origin: np.ndarray, parent_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A body's ``pos`` and ``quat`` in its parent's frame."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, (parent_frame.T @ link.frame).ravel())
    return parent_frame.T @ (link.origin - parent_origin), quat


def _numbers(values: Any) -> str:
    return " ".join(f"{float(v):.12g}" for v in np.ravel(values))


def _write(link: _Link, parent_origin: np.ndarray, parent_frame: np.ndarray, depth: int) -> list[str]:
    pad = "  " * depth
    pos, quat = _place(link, parent_origin, parent_frame)
    local = link.frame.T
    lines = [f'{pad}<body name="{link.name}" pos="{_numbers(pos)}" quat="{_numbers(quat)}">']
    for joint in link.joints:
        extra = "".join(f' {key}="{value:.12g}"' for key, value in joint.attributes.items())
        if joint.limit is not None:
            extra += f' limited="true" range="{_numbers(joint.limit)}"'
        axis = "" if joint.kind == "ball" else f' axis="{_numbers(local @ joint.axis)}"'
        lines.append(f'{pad}  <joint name="{joint.name}" type="{joint.kind}"{axis}{extra}/>')
    tip = local @ (link.tip - link.origin)
    if link.inertial is None:
        radius = 0.02 + 0.03 * (link.mass / 2.0)
        lines.append(f'{pad}  <geom name="{link.name}_geom" type="capsule" fromto="0 0 0 {_numbers(tip)}" '
                     f'size="{radius:.6g}" mass="{link.mass:.12g}"/>')
    else:
        center = local @ (link.inertial["center"] - link.origin)
        inertia = local @ link.inertial["inertia"] @ local.T
        full = [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]]
        lines.append(f'{pad}  <inertial pos="{_numbers(center)}" mass="{link.mass:.12g}" '
                     f'fullinertia="{_numbers(full)}"/>')
        lines.append(f'{pad}  <geom name="{link.name}_geom" type="capsule" fromto="0 0 0 {_numbers(tip)}" size="0.01" '
                     f'mass="0" contype="0" conaffinity="0"/>')
    for site, (position, frame) in link.sites.items():
        site_quat = np.zeros(4)
        mujoco.mju_mat2Quat(site_quat, (local @ frame).ravel())
        lines.append(f'{pad}  <site name="{site}" pos="{_numbers(local @ (position - link.origin))}" '
                     f'quat="{_numbers(site_quat)}"/>')
    for child in link.children:
        lines += _write(child, link.origin, link.frame, depth + 1)
    lines.append(f"{pad}</body>")
    return lines


def _frame_along(axis: np.ndarray) -> np.ndarray:
    """A site frame whose x axis is ``axis`` (so gear ``1 0 0`` pushes, ``0 0 0 1 0 0`` turns, along it)."""
    y = _across(axis, np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0]))
    return np.column_stack([axis, y, np.cross(axis, y)])


# ----------------------------------------------------------------------------- the kinds
def _chain(rng: np.random.Generator, prefix: str, start: np.ndarray, directions: list[np.ndarray],
           joints: list[list[_Joint]]) -> list[_Link]:
    """Links one below the other, each starting at its parent's tip."""
    links: list[_Link] = []
    origin = start
    for i, (direction, link_joints) in enumerate(zip(directions, joints)):
        link = _link(rng, f"{prefix}{i + 1}", origin, direction, link_joints)
        if links:
            links[-1].children.append(link)
        links.append(link)
        origin = link.tip
    return links


def _cart_pole(rng: np.random.Generator, seed: int) -> tuple[_Link, list[str], dict[str, Any]]:
    heading = rng.uniform(0.0, 2.0 * math.pi)
    rail = np.array([math.cos(heading), math.sin(heading), 0.0])
    across = _across(np.array([0.0, 0.0, 1.0]), rail)
    slide = _joint(rng, "rail", "slide", rail)
    if rng.uniform() < 0.5:
        travel = float(rng.uniform(1.0, 3.0))
        slide.limit = (-travel, travel)
    cart = _link(rng, "cart", np.zeros(3), np.array([0.0, 0.0, 1.0]), [slide], mass=_log_draw(rng, 0.2, 3.0),
                 length=0.1)
    poles = int(rng.choice([1, 2, 3], p=[0.5, 0.35, 0.15]))
    hinges = [[_joint(rng, f"pole{i + 1}_hinge", "hinge", _tilted(rng, across, 15.0))] for i in range(poles)]
    links = _chain(rng, "pole", cart.tip, [np.array([0.0, 0.0, 1.0])] * poles, hinges)
    cart.children.append(links[0])
    actuators = []
    if rng.uniform() < 0.5:
        actuators.append(f'<motor name="push" joint="rail" gear="{_gear(rng):.12g}"/>')
    else:
        cart.sites["push_site"] = (cart.origin, _frame_along(rail))
        actuators.append(f'<motor name="push" site="push_site" gear="{_gear(rng):.12g} 0 0 0 0 0"/>')
    if rng.uniform() < 0.25:
        actuators.append(f'<motor name="pole_motor" joint="pole1_hinge" gear="{_gear(rng):.12g}"/>')
    return cart, actuators, {"poles": poles, "rail": rail.tolist()}


def _double_pendulum(rng: np.random.Generator, seed: int) -> tuple[_Link, list[str], dict[str, Any]]:
    heading = rng.uniform(0.0, 2.0 * math.pi)
    axis = np.array([math.cos(heading), math.sin(heading), 0.0])
    count = int(rng.choice([2, 3], p=[0.7, 0.3]))
    planar = rng.uniform() >= 0.3
    axes = [axis if planar or i == 0 else _tilted(rng, axis, 30.0) for i in range(count)]
    hinges = [[_joint(rng, "shoulder" if i == 0 else f"elbow{i}" if count > 2 else "elbow", "hinge", a)]
              for i, a in enumerate(axes)]
    links = _chain(rng, "link", np.zeros(3), [_DOWN] * count, hinges)
    actuation = ("pendubot", "acrobot", "full")[seed % 3]
    driven = {"pendubot": [0], "acrobot": [1], "full": list(range(count))}[actuation]
    actuators = [f'<motor name="{hinges[i][0].name}_motor" joint="{hinges[i][0].name}" gear="{_gear(rng):.12g}"/>'
                 for i in driven]
    return links[0], actuators, {"links": count, "planar": planar, "actuation": actuation}


def _furuta(rng: np.random.Generator, seed: int) -> tuple[_Link, list[str], dict[str, Any]]:
    vertical = _tilted(rng, np.array([0.0, 0.0, 1.0]), 10.0)
    heading = rng.uniform(0.0, 2.0 * math.pi)
    along = np.array([math.cos(heading), math.sin(heading), 0.0])
    along = along - (along @ vertical) * vertical
    along /= np.linalg.norm(along)
    arm = _link(rng, "arm", np.zeros(3), along, [_joint(rng, "arm_hinge", "hinge", vertical)])
    count = int(rng.choice([1, 2], p=[0.7, 0.3]))
    hinges = [[_joint(rng, f"pendulum{i + 1}_hinge", "hinge", along)] for i in range(count)]
    links = _chain(rng, "pendulum", arm.tip, [_DOWN] * count, hinges)
    arm.children.append(links[0])
    if rng.uniform() < 0.5:
        actuators = [f'<motor name="arm_motor" joint="arm_hinge" gear="{_gear(rng):.12g}"/>']
    else:
        arm.sites["arm_site"] = (arm.origin + 0.3 * (arm.tip - arm.origin), _frame_along(vertical))
        actuators = [f'<motor name="arm_motor" site="arm_site" gear="0 0 0 {_gear(rng):.12g} 0 0"/>']
    return arm, actuators, {"pendulum_links": count}


def _ball_arm(rng: np.random.Generator, seed: int) -> tuple[_Link, list[str], dict[str, Any]]:
    upper_direction = _tilted(rng, _DOWN, 60.0)
    elbow = ("hinge", "ball", "hinge+wrist")[seed % 3]
    upper = _link(rng, "upper_arm", np.zeros(3), upper_direction, [_joint(rng, "shoulder", "ball")])
    elbow_axis = _across(upper_direction, rng.normal(size=3))
    elbow_joint = _joint(rng, "elbow", "ball" if elbow == "ball" else "hinge", elbow_axis)
    lower = _link(rng, "forearm", upper.tip, _tilted(rng, upper_direction, 45.0), [elbow_joint])
    upper.children.append(lower)
    if elbow == "hinge+wrist":
        wrist = _joint(rng, "wrist", "hinge", _across(lower.tip - lower.origin, rng.normal(size=3)))
        lower.children.append(_link(rng, "hand", lower.tip, _tilted(rng, upper_direction, 45.0), [wrist]))
    shoulder_motors = int(rng.choice([2, 3]))
    transmission = ("joint", "jointinparent", "site")[seed % 3]
    actuators = []
    for i in range(shoulder_motors):
        direction = rng.normal(size=3)
        direction = _gear(rng) * direction / np.linalg.norm(direction)
        if transmission == "site":
            site = f"shoulder_site{i}"
            upper.sites[site] = (upper.origin + 0.5 * (upper.tip - upper.origin), _uniform_rotation(rng))
            actuators.append(f'<motor name="shoulder_motor{i}" site="{site}" gear="0 0 0 {_numbers(direction)}"/>')
        else:
            actuators.append(f'<motor name="shoulder_motor{i}" {transmission}="shoulder" '
                             f'gear="{_numbers(direction)} 0 0 0"/>')
    if elbow_joint.kind == "hinge" and rng.uniform() < 0.7:
        actuators.append(f'<motor name="elbow_motor" joint="elbow" gear="{_gear(rng):.12g}"/>')
    return upper, actuators, {"elbow": elbow, "shoulder_motors": shoulder_motors, "shoulder_transmission": transmission}


_BUILDERS = {"cart_pole": _cart_pole, "double_pendulum": _double_pendulum, "furuta": _furuta, "ball_arm": _ball_arm}


def mechanism_scene(kind: str, seed: int) -> tuple[str, dict[str, Any]]:
    """The MJCF of the family's ``(kind, seed)`` member and its drawn facts (module docstring).

    Raises:
        ValueError: an unknown ``kind``.
    """
    if kind not in _BUILDERS:
        raise ValueError(f"unknown mechanism kind {kind!r}; expected one of {', '.join(KINDS)}")
    rng = np.random.default_rng([int(seed), KINDS.index(kind)])
    root, actuators, facts = _BUILDERS[kind](rng, int(seed))
    gravity = float(rng.uniform(1.6, 9.81))
    timestep = float(rng.uniform(0.002, 0.01))
    integrator = str(rng.choice(["Euler", "RK4", "implicitfast"]))
    name = f"{kind}_{seed}"
    lines = [f'<mujoco model="{name}">',
             '  <compiler angle="radian" autolimits="true"/>',
             f'  <option timestep="{timestep:.6g}" gravity="0 0 {-gravity:.12g}" integrator="{integrator}">',
             '    <flag contact="disable" energy="enable"/>',
             "  </option>",
             "  <worldbody>",
             *_write(root, np.array([0.0, 0.0, -2.0]), np.eye(3), 2),
             "  </worldbody>",
             "  <actuator>",
             *(f"    {line[:-2]} ctrlrange=\"-1 1\"/>" for line in actuators),
             "  </actuator>",
             "</mujoco>"]
    facts = {"kind": kind, "seed": int(seed), "gravity": gravity, "timestep": timestep, "integrator": integrator,
             "actuators": len(actuators), **facts}
    return "\n".join(lines) + "\n", facts


def mechanism_mjcf(kind: str, seed: int) -> str:
    """The MJCF text of the family's ``(kind, seed)`` member (:func:`mechanism_scene`)."""
    return mechanism_scene(kind, seed)[0]


# ----------------------------------------------------------------------------- the oracle
def random_joint_states(model: mujoco.MjModel, rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random ``(qpos, qvel)`` of ``model``: angles and travels ~N(0, 1.5²), every ball's and free
    joint's quaternion uniform on S³, rates ~N(0, 2²)."""
    qpos = 1.5 * rng.normal(size=(count, model.nq))
    for joint in range(model.njnt):
        kind, start = int(model.jnt_type[joint]), int(model.jnt_qposadr[joint])
        offset = {int(mujoco.mjtJoint.mjJNT_FREE): 3, int(mujoco.mjtJoint.mjJNT_BALL): 0}.get(kind)
        if offset is not None:
            quat = rng.normal(size=(count, 4))
            qpos[:, start + offset:start + offset + 4] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    return qpos, 2.0 * rng.normal(size=(count, model.nv))


def mujoco_terms(model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray) -> dict[str, Any]:
    """MuJoCo at one state: ``mass`` (``mj_fullM``), ``bias`` (``qfrc_bias``), ``passive`` (``qfrc_passive``),
    ``moment`` (``actuator_moment``, dense ``nu × nv``), ``potential`` and ``kinetic`` (``energy``; the
    model's energy flag on)."""
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = qpos, qvel
    mujoco.mj_forward(model, data)
    mass, moment = np.zeros((model.nv, model.nv)), np.zeros((model.nu, model.nv))
    mujoco.mj_fullM(model, data, mass)
    mujoco.mju_sparse2dense(moment, data.actuator_moment, data.moment_rownnz, data.moment_rowadr, data.moment_colind)
    return {"mass": mass, "bias": data.qfrc_bias.copy(), "passive": data.qfrc_passive.copy(), "moment": moment,
            "potential": float(data.energy[0]), "kinetic": float(data.energy[1])}


#: The terms :func:`closed_form_errors` compares.
TERMS = ("mass", "bias", "passive", "moment", "energy")


def closed_form_errors(model: mujoco.MjModel, seed: int, states: int = 10) -> dict[str, dict[str, float]]:
    """The closed form (:class:`~fvin_mpc.core.tree_dynamics.KinematicTree`, NumPy, all states at once)
    against MuJoCo at ``states`` random states (:func:`random_joint_states` of ``default_rng(seed)``):
    ``{"error": …, "scale": …}``, each ``term → value`` over :data:`TERMS` — the largest absolute
    difference, and the largest absolute entry of MuJoCo's value (the energy's: potential and kinetic) — and
    ``"mass"``: the smallest eigenvalue of ``M`` and the largest asymmetry ``|M − Mᵀ|``."""
    tree = KinematicTree.from_mujoco(model)
    qpos, qvel = random_joint_states(model, np.random.default_rng(seed), states)
    ours = tree.numpy_terms(qpos, qvel)
    positions, rates = NP_OPS.unstack(qpos), NP_OPS.unstack(qvel)
    ours["potential"] = np.broadcast_to(tree.potential_energy(positions, NP_OPS), (states,))
    ours["kinetic"] = tree.kinetic_energy(positions, rates, NP_OPS)
    error, scale = dict.fromkeys(TERMS, 0.0), dict.fromkeys(TERMS, 0.0)
    for i in range(states):
        theirs = mujoco_terms(model, qpos[i], qvel[i])
        for name in TERMS:
            parts = ("potential", "kinetic") if name == "energy" else (name,)
            for part in parts:
                difference = np.abs(np.asarray(ours[part][i]) - theirs[part])
                error[name] = max(error[name], float(np.max(difference, initial=0.0)))
                scale[name] = max(scale[name], float(np.max(np.abs(theirs[part]), initial=0.0)))
    mass = ours["mass"]
    return {"error": error, "scale": scale,
            "mass": {"smallest_eigenvalue": float(np.linalg.eigvalsh(mass).min()),
                     "asymmetry": float(np.abs(mass - np.swapaxes(mass, -1, -2)).max())}}

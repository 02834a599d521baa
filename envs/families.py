"""Random scene families: seeded MJCFs of one rigid body on a hinge or a ball joint, drawn over the
ranges a user could plausibly bring, and the check that names what an MJCF has outside them.

``hinge_scene(seed)`` and ``ball_scene(seed)`` return ``(mjcf_text, facts)``: a self-contained MJCF
(one body under the world, rigidly attached child bodies allowed, one joint, ``motor`` actuators with
``ctrlrange``) and the drawn parameters. Everything comes from ``numpy.random.default_rng(seed)``, so
a seed is a scene. :func:`write_family` writes ``<kind>_<seed>.xml`` files (and the facts beside them
as JSON) that any command takes as ``--scene PATH``.

What a hinge draw is (:data:`HINGE_RANGES`):

* a body of mass 0.1–5 kg (log-uniform): a point mass (a 2 cm sphere), a uniform rod (a capsule
  whose midpoint is the centre of mass, the pivot anywhere from its end to a third of the way in),
  or a composite (2–4 geoms of random shape, size, pose and mass in the body, plus 1–2 child bodies
  *without joints*, each with 1–2 geoms, at random poses);
* its centre of mass 0.1–1.5 m from the pivot, in a random direction of the body's frame at least 30°
  from the hinge axis (so possibly off the body's axes and with a component along the hinge axis);
* the hinge axis in a random world direction at least 30° from gravity, and the body's frame at
  ``qpos = 0`` a uniformly random rotation: upright and hanging fall at whatever ``qpos`` the draw
  makes them (the package reads them off the potential; nothing assumes ``qpos = 0`` hangs);
* joint damping: none (30 % of draws) or a damping ratio ``ζ`` uniform in (0, 0.5] about the hanging
  equilibrium, ``b = 2ζ√(k J)`` with ``k`` the largest gravity torque and ``J`` the inertia about the
  axis including armature; armature: none (half the draws) or up to half the body's inertia about
  the axis;
* one ``motor`` with gear ±(0.1–100) (log-uniform, random sign) and a torque bound of 0.15–1.5× the
  largest gravity torque (``ctrlrange`` = bound / |gear|);
* timestep 1–20 ms (0.1 ms grid), integrator Euler, RK4 or implicitfast, gravity 1.6–9.81 m/s².

A ball draw is the same on a ball joint (any direction has gravity torque) with a flywheel disk at the
centre of mass sized so that the inertia about the long axis (pivot to centre of mass) over the
largest transverse one is a drawn ratio, log-uniform in 1:50–1:1 (the measured ratio is in the facts);
and either 3 motors about the body's axes or 2 about the two axes perpendicular to the long axis
(then nothing acts on the spin about the long axis, and a run is judged on tilt only).

:func:`unsupported_features` lists what an MJCF has that a pivoted scene cannot take (chains of
jointed bodies, tendons, equality constraints, actuators with dynamics, bias or gain, ...);
:func:`refusal` is its one-line message.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Iterable

import mujoco
import numpy as np

from .scenes import can_collide

FAMILIES = ("hinge", "ball")

#: The ranges of a draw (see the module docstring).
HINGE_RANGES: dict[str, Any] = {
    "mass_kg": (0.1, 5.0),
    "com_distance_m": (0.1, 1.5),
    "axis_from_gravity_min_deg": 30.0,
    "damping_ratio": (0.0, 0.5),
    "armature_fraction": (0.0, 0.5),
    "gear_abs": (0.1, 100.0),
    "torque_bound_ratio": (0.15, 1.5),
    "timestep_s": (0.001, 0.02),
    "gravity": (1.6, 9.81),
    "body_kinds": ("point", "rod", "composite"),
    "integrators": ("Euler", "RK4", "implicitfast"),
}
BALL_RANGES: dict[str, Any] = {**HINGE_RANGES, "inertia_ratio": (1.0 / 50.0, 1.0), "actuators": (2, 3)}
del BALL_RANGES["axis_from_gravity_min_deg"]

_SHAPES = ("sphere", "capsule", "box", "cylinder", "ellipsoid")
_NO_CONTACT = 'contype="0" conaffinity="0"'


# ----------------------------------------------------------------------------- small geometry helpers
def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def _matrix(q: np.ndarray) -> np.ndarray:
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.asarray(q, dtype=float))
    return m.reshape(3, 3)


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _unit_away_from(rng: np.random.Generator, direction: np.ndarray, min_angle_deg: float) -> np.ndarray:
    """A uniformly random unit vector at least ``min_angle_deg`` from ``±direction``."""
    limit = math.cos(math.radians(min_angle_deg))
    while True:
        v = _unit(rng)
        if abs(float(v @ direction)) <= limit:
            return v


def _perpendicular_basis(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.eye(3)[int(np.argmin(np.abs(u)))]
    v1 = np.cross(u, helper)
    v1 /= np.linalg.norm(v1)
    return v1, np.cross(u, v1)


def _quat_z_to(u: np.ndarray) -> np.ndarray:
    """A quaternion turning +z onto unit ``u`` (for a geom's axis)."""
    q = np.zeros(4)
    mujoco.mju_quatZ2Vec(q, np.asarray(u, dtype=float))
    return q


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


def _fmt(values: Iterable[float]) -> str:
    return " ".join(f"{float(v):.10g}" for v in values)


# ----------------------------------------------------------------------------- parts of a body
def _geom(
    shape: str, mass: float, pos: np.ndarray, quat: np.ndarray, size: Iterable[float], name: str
) -> dict[str, Any]:
    return {
        "type": shape,
        "mass": float(mass),
        "pos": np.asarray(pos, dtype=float),
        "quat": np.asarray(quat, dtype=float),
        "size": [float(s) for s in size],
        "name": name,
    }


def _random_geom(rng: np.random.Generator, mass: float, scale: float, name: str) -> dict[str, Any]:
    shape = str(rng.choice(_SHAPES))
    dims = scale * rng.uniform(0.05, 0.3, size=3)
    size = {"sphere": dims[:1], "capsule": dims[:2], "cylinder": dims[:2], "box": dims, "ellipsoid": dims}[shape]
    return _geom(shape, mass, scale * rng.uniform(-1.0, 1.0, size=3), _random_rotation(rng), size, name)


def _geom_xml(g: dict[str, Any], shift: np.ndarray) -> str:
    return (
        f'<geom name="{g["name"]}" type="{g["type"]}" size="{_fmt(g["size"])}" pos="{_fmt(g["pos"] + shift)}" '
        f'quat="{_fmt(g["quat"])}" mass="{g["mass"]:.10g}" {_NO_CONTACT}/>'
    )


def _body_parts(rng: np.random.Generator, kind: str, mass: float, com: np.ndarray) -> tuple[list, list]:
    """``(geoms, children)`` in the body's frame, pivot at the origin, centre of mass not yet placed
    (a composite is shifted afterwards); each child is ``{"pos", "quat", "geoms"}``."""
    r = float(np.linalg.norm(com))
    u = com / r
    if kind == "point":
        return [_geom("sphere", mass, com, np.array([1.0, 0, 0, 0]), [0.02], "point")], []
    if kind == "rod":
        overhang = rng.uniform(0.0, 0.5) * r  # the pivot from the rod's end up to a third of its length in
        half = r + overhang
        radius = min(0.05, 0.1 * half) * rng.uniform(0.2, 1.0)
        return [_geom("capsule", mass, com, _quat_z_to(u), [radius, half], "rod")], []
    masses = mass * rng.dirichlet(np.ones(int(rng.integers(3, 7))))
    n_body = int(rng.integers(2, 5)) if masses.size > 3 else 2
    geoms = [_random_geom(rng, m, r, f"part{i}") for i, m in enumerate(masses[:n_body])]
    rest = list(masses[n_body:])
    children = []
    while rest:
        take = min(len(rest), int(rng.integers(1, 3)))
        pos = r * rng.uniform(-1.0, 1.0, size=3)
        child_geoms = [_random_geom(rng, m, 0.5 * r, f"child{len(children)}_{i}") for i, m in enumerate(rest[:take])]
        children.append({"pos": pos, "quat": _random_rotation(rng), "geoms": child_geoms})
        rest = rest[take:]
    return geoms, children


def _mjcf(
    name: str,
    joint_xml: str,
    body_quat: np.ndarray,
    geoms: list,
    children: list,
    shift: np.ndarray,
    actuators_xml: str,
    timestep: float,
    gravity: float,
    integrator: str,
) -> str:
    lines = [
        f'<mujoco model="{name}">',
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <option timestep="{timestep:.10g}" gravity="0 0 {-gravity:.10g}" integrator="{integrator}"/>',
        "  <worldbody>",
        f'    <body name="body" pos="0 0 2" quat="{_fmt(body_quat)}">',
        f"      {joint_xml}",
    ]
    lines += [f"      {_geom_xml(g, shift)}" for g in geoms]
    for i, child in enumerate(children):
        lines.append(f'      <body name="child{i}" pos="{_fmt(child["pos"] + shift)}" quat="{_fmt(child["quat"])}">')
        lines += [f"        {_geom_xml(g, np.zeros(3))}" for g in child["geoms"]]
        lines.append("      </body>")
    lines += ["    </body>", "  </worldbody>", "  <actuator>", actuators_xml, "  </actuator>", "</mujoco>", ""]
    return "\n".join(lines)


def _subtree_com_in_body(model: mujoco.MjModel) -> np.ndarray:
    """The centre of mass of the jointed body's subtree, in its frame, relative to the joint's anchor."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    body = 1
    frame = data.xmat[body].reshape(3, 3)
    return frame.T @ (data.subtree_com[body] - data.xanchor[0])


def _joint_space_inertia(model: mujoco.MjModel) -> np.ndarray:
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, full)
    return full


def _placed(geoms: list, children: list, com: np.ndarray, build) -> np.ndarray:
    """The shift that puts the subtree's centre of mass at ``com`` (compiling a draft)."""
    draft = mujoco.MjModel.from_xml_string(build(np.zeros(3)))
    return com - _subtree_com_in_body(draft)


# ----------------------------------------------------------------------------- the families
def _common(rng: np.random.Generator, ranges: dict[str, Any]) -> dict[str, Any]:
    return {
        "kind": str(rng.choice(ranges["body_kinds"])),
        "mass_kg": _log_uniform(rng, *ranges["mass_kg"]),
        "com_distance_m": float(rng.uniform(*ranges["com_distance_m"])),
        "gravity": float(rng.uniform(*ranges["gravity"])),
        "timestep_s": round(float(rng.uniform(*ranges["timestep_s"])), 4),
        "integrator": str(rng.choice(ranges["integrators"])),
        "body_quat": _random_rotation(rng),
        "damped": bool(rng.uniform() >= 0.3),
        "damping_ratio": float(rng.uniform(1e-3, ranges["damping_ratio"][1])),
        "with_armature": bool(rng.uniform() >= 0.5),
        "armature_fraction": float(rng.uniform(1e-3, ranges["armature_fraction"][1])),
        "gear": float(rng.choice([-1.0, 1.0]) * _log_uniform(rng, *ranges["gear_abs"])),
        "torque_bound_ratio": float(rng.uniform(*ranges["torque_bound_ratio"])),
    }


def _actuation_and_simulation_facts(draw: dict[str, Any], gravity_torque: float, bound: float,
                                    children: list[Any]) -> dict[str, Any]:
    """The facts every family's draw reports about its motor bound and its simulation, in report order."""
    return {"torque_bound_ratio": draw["torque_bound_ratio"], "gravity_torque_max": gravity_torque,
            "ctrl_bound": bound, "timestep_s": draw["timestep_s"], "gravity": draw["gravity"],
            "integrator": draw["integrator"], "child_bodies": len(children)}


def hinge_scene(seed: int) -> tuple[str, dict[str, Any]]:
    """One draw of the hinge family: ``(mjcf_text, facts)`` (module docstring)."""
    rng = np.random.default_rng(seed)
    draw = _common(rng, HINGE_RANGES)
    world_axis = _unit_away_from(rng, np.array([0.0, 0.0, 1.0]), HINGE_RANGES["axis_from_gravity_min_deg"])
    body_rotation = _matrix(draw["body_quat"])
    axis = body_rotation.T @ world_axis  # the axis in the body's frame
    com = draw["com_distance_m"] * _unit_away_from(rng, axis, 30.0)
    geoms, children = _body_parts(rng, draw["kind"], draw["mass_kg"], com)
    name = f"hinge_{seed}"

    def build(
        shift: np.ndarray, joint_extra: str = "", actuator: str = '    <motor name="motor" joint="hinge"/>'
    ) -> str:
        joint = f'<joint name="hinge" type="hinge" pos="0 0 0" axis="{_fmt(axis)}"{joint_extra}/>'
        return _mjcf(name, joint, draw["body_quat"], geoms, children, shift, actuator, draw["timestep_s"],
                     draw["gravity"], draw["integrator"])

    shift = _placed(geoms, children, com, build)
    inertia_axis = float(_joint_space_inertia(mujoco.MjModel.from_xml_string(build(shift)))[0, 0])
    armature = draw["armature_fraction"] * inertia_axis if draw["with_armature"] else 0.0
    com_perp = com - float(com @ axis) * axis
    sin_tilt = math.sqrt(max(0.0, 1.0 - float(world_axis[2]) ** 2))  # axis vs gravity
    gravity_torque = draw["mass_kg"] * draw["gravity"] * float(np.linalg.norm(com_perp)) * sin_tilt
    stiffness = gravity_torque  # d²U/dθ² at the hanging equilibrium
    zeta = draw["damping_ratio"] if draw["damped"] else 0.0
    damping = 2.0 * zeta * math.sqrt(stiffness * (inertia_axis + armature))
    bound = draw["torque_bound_ratio"] * gravity_torque / abs(draw["gear"])
    joint_extra = f' damping="{damping:.10g}"' + (f' armature="{armature:.10g}"' if armature else "")
    actuator = (
        f'    <motor name="motor" joint="hinge" gear="{draw["gear"]:.10g}" ctrllimited="true" '
        f'ctrlrange="{-bound:.10g} {bound:.10g}"/>'
    )
    text = build(shift, joint_extra, actuator)
    facts = {
        "family": "hinge",
        "seed": int(seed),
        "kind": draw["kind"],
        "mass_kg": draw["mass_kg"],
        "com_distance_m": draw["com_distance_m"],
        "com_body": [float(c) for c in com],
        "axis_body": [float(a) for a in axis],
        "axis_world": [float(a) for a in world_axis],
        "axis_from_gravity_deg": math.degrees(math.acos(min(1.0, abs(float(world_axis[2]))))),
        "body_quat": [float(q) for q in draw["body_quat"]],
        "damping_ratio": zeta,
        "damping": damping,
        "armature": armature,
        "inertia_axis": inertia_axis,
        "gear": draw["gear"],
        **_actuation_and_simulation_facts(draw, gravity_torque, bound, children),
    }
    return text, facts


def ball_scene(seed: int, actuators: int | None = None) -> tuple[str, dict[str, Any]]:
    """One draw of the ball family: ``(mjcf_text, facts)`` (module docstring); ``actuators`` (2 or 3)
    fixes the number of motors instead of drawing it."""
    rng = np.random.default_rng(seed)
    draw = _common(rng, BALL_RANGES)
    n_act = int(rng.choice(BALL_RANGES["actuators"])) if actuators is None else int(actuators)
    if n_act not in (2, 3):
        raise ValueError(f"a ball scene has 2 or 3 actuators, got {actuators!r}")
    target_ratio = _log_uniform(rng, *BALL_RANGES["inertia_ratio"])
    disk_share = float(rng.uniform(0.3, 0.8))
    u = _unit(rng)
    com = draw["com_distance_m"] * u
    mass = draw["mass_kg"]
    geoms, children = _body_parts(rng, draw["kind"], (1.0 - disk_share) * mass, com)
    name = f"ball_{seed}"
    disk = {"geom": None}

    def build(
        shift: np.ndarray,
        joint_extra: str = "",
        actuator: str = '    <motor name="m0" joint="ball" gear="1 0 0 0 0 0"/>',
    ) -> str:
        joint = f'<joint name="ball" type="ball" pos="0 0 0"{joint_extra}/>'
        parts = geoms + ([disk["geom"]] if disk["geom"] is not None else [])
        return _mjcf(name, joint, draw["body_quat"], parts, children, shift, actuator, draw["timestep_s"],
                     draw["gravity"], draw["integrator"])

    shift = _placed(geoms, children, com, build)
    # The flywheel disk at the centre of mass, its axis along u: its radius sets I_long / I_transverse.
    rest_inertia = _joint_space_inertia(mujoco.MjModel.from_xml_string(build(shift)))
    long0 = float(u @ rest_inertia @ u)
    v1, v2 = _perpendicular_basis(u)
    transverse = np.array(
        [[v1 @ rest_inertia @ v1, v1 @ rest_inertia @ v2], [v2 @ rest_inertia @ v1, v2 @ rest_inertia @ v2]]
    )
    trans0 = float(np.linalg.eigvalsh(transverse).max())
    m_disk, r = disk_share * mass, draw["com_distance_m"]
    half_height = 0.01 * r
    radius_sq = (target_ratio * (trans0 + m_disk * (r * r + half_height**2 / 3.0)) - long0) / (
        m_disk * (0.5 - target_ratio / 4.0)
    )
    radius = math.sqrt(max(radius_sq, (0.02 * r) ** 2))
    disk["geom"] = _geom("cylinder", m_disk, com - shift, _quat_z_to(u), [radius, half_height], "flywheel")
    inertia = _joint_space_inertia(mujoco.MjModel.from_xml_string(build(shift)))
    long_axis = float(u @ inertia @ u)
    transverse = np.array([[v1 @ inertia @ v1, v1 @ inertia @ v2], [v2 @ inertia @ v1, v2 @ inertia @ v2]])
    trans_max = float(np.linalg.eigvalsh(transverse).max())
    armature = draw["armature_fraction"] * float(np.linalg.eigvalsh(inertia).min()) if draw["with_armature"] else 0.0
    gravity_torque = mass * draw["gravity"] * r
    zeta = draw["damping_ratio"] if draw["damped"] else 0.0
    damping = 2.0 * zeta * math.sqrt(gravity_torque * (trans_max + armature))
    gear = draw["gear"]
    bound = draw["torque_bound_ratio"] * gravity_torque / abs(gear)
    directions = list(np.eye(3)) if n_act == 3 else [v1, v2]
    actuator = "\n".join(
        f'    <motor name="m{i}" joint="ball" gear="{_fmt(gear * d)} 0 0 0" ctrllimited="true" '
        f'ctrlrange="{-bound:.10g} {bound:.10g}"/>'
        for i, d in enumerate(directions)
    )
    joint_extra = f' damping="{damping:.10g}"' + (f' armature="{armature:.10g}"' if armature else "")
    text = build(shift, joint_extra, actuator)
    facts = {
        "family": "ball",
        "seed": int(seed),
        "kind": draw["kind"],
        "mass_kg": mass,
        "com_distance_m": r,
        "com_body": [float(c) for c in com],
        "long_axis_body": [float(c) for c in u],
        "body_quat": [float(q) for q in draw["body_quat"]],
        "actuators": n_act,
        "inertia_ratio_target": target_ratio,
        "inertia_ratio": long_axis / trans_max,
        "damping_ratio": zeta,
        "damping": damping,
        "armature": armature,
        "gear": gear,
        **_actuation_and_simulation_facts(draw, gravity_torque, bound, children),
        "judged_on": "tilt" if n_act == 2 else "orientation",
    }
    return text, facts


SCENE_FUNCTIONS = {"hinge": hinge_scene, "ball": ball_scene}


def family_scene(kind: str, seed: int) -> tuple[str, dict[str, Any]]:
    """:func:`hinge_scene` or :func:`ball_scene` by name."""
    if kind not in SCENE_FUNCTIONS:
        raise ValueError(f"unknown family {kind!r}: expected one of {FAMILIES}")
    return SCENE_FUNCTIONS[kind](seed)


def write_family(kind: str, seeds: Iterable[int], directory: str | Path) -> list[Path]:
    """Write ``<kind>_<seed>.xml`` (and ``<kind>_<seed>.json``, its facts) for each seed into
    ``directory``; returns the MJCF paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for seed in seeds:
        text, facts = family_scene(kind, int(seed))
        path = directory / f"{kind}_{int(seed)}.xml"
        path.write_text(text)
        path.with_suffix(".json").write_text(json.dumps(facts, indent=2) + "\n")
        paths.append(path)
    return paths


# ----------------------------------------------------------------------------- what is out of family
def unsupported_features(model: mujoco.MjModel, structure_only: bool = False) -> list[str]:
    """What a compiled MJCF has that a scene of one rigid body on one actuated hinge or ball joint
    (:class:`~envs.rigid_body_env.RigidBodyEnv`, the closed form of
    :func:`~fvin_mpc.core.rigid_body.from_mujoco`) cannot take; empty if nothing.

    A body with a free joint (the quadrotor's R³ × S³ scenes) is not flagged when it is the model's
    only joint: that is another configuration space, not an unsupported feature. ``structure_only``:
    only what no physics declaration can switch off (bodies, joints, tendons, equalities, actuator
    kinds) — the effects (springs, limits, friction, contact, gravity, torque bounds) are the scene
    declaration's to accept or refuse (:func:`envs.scenes.check_unsupported_effects`).
    """
    problems: list[str] = []
    jointed = [b for b in range(1, model.nbody) if model.body_jntnum[b] > 0]
    free = int(mujoco.mjtJoint.mjJNT_FREE)
    if len(jointed) > 1:
        problems.append(f"a chain of jointed bodies ({len(jointed)} bodies with joints)")
    if any(model.body_jntnum[b] > 1 for b in jointed):
        problems.append("a body with several joints")
    slides = int(np.sum(model.jnt_type == int(mujoco.mjtJoint.mjJNT_SLIDE)))
    if slides:
        problems.append(f"slide joints ({slides})")
    if model.njnt == 0:
        problems.append("no joint")
    elif not (model.njnt == 1 and int(model.jnt_type[0]) == free) and np.any(model.jnt_type == free):
        problems.append("a free joint beside other joints")
    if model.ntendon > 0:
        problems.append(f"tendons ({model.ntendon})")
    if model.neq > 0:
        problems.append(f"equality constraints ({model.neq})")
    if getattr(model, "nflex", 0) > 0:
        problems.append("flexible bodies (flex)")
    if model.nmocap > 0:
        problems.append("mocap bodies")
    effects_too = not structure_only
    if effects_too and np.any(model.jnt_stiffness != 0.0):
        problems.append("joint springs (stiffness)")
    if effects_too and np.any(model.jnt_limited):
        problems.append("joint limits")
    if effects_too and np.any(model.dof_frictionloss > 0.0):
        problems.append("joint dry friction (frictionloss)")
    if model.nu == 0:
        problems.append("no actuator")
    none_dyn, none_bias = int(mujoco.mjtDyn.mjDYN_NONE), int(mujoco.mjtBias.mjBIAS_NONE)
    fixed_gain, joint_trn = int(mujoco.mjtGain.mjGAIN_FIXED), int(mujoco.mjtTrn.mjTRN_JOINT)
    if np.any(model.actuator_dyntype != none_dyn) or model.na > 0:
        problems.append("actuators with dynamics (dyntype, activation state)")
    if np.any(model.actuator_biastype != none_bias):
        problems.append("actuators with bias (position/velocity servos, biastype)")
    if np.any(model.actuator_gaintype != fixed_gain) or (model.nu and np.any(model.actuator_gainprm[:, 0] != 1.0)):
        problems.append("actuators with a gain other than 1 (only motors' gear scales the torque)")
    if np.any(model.actuator_trntype != joint_trn):
        problems.append("actuators not on a joint (tendon, site or body transmission)")
    if structure_only:
        return problems
    if model.nu and not np.all(model.actuator_ctrllimited):
        problems.append("actuators without a ctrlrange (the controllers need torque bounds)")
    gravity = np.asarray(model.opt.gravity, dtype=float)
    if gravity[0] != 0.0 or gravity[1] != 0.0:
        problems.append("gravity not along −z")
    if can_collide(model):
        problems.append("geoms that can collide (contact)")
    return problems


def refusal(model: mujoco.MjModel, name: str = "the MJCF", structure_only: bool = False) -> str | None:
    """One line naming what :func:`unsupported_features` found, or ``None``."""
    problems = unsupported_features(model, structure_only)
    if not problems:
        return None
    return f"{name} is outside what the package supports: {'; '.join(problems)}"

"""A random family of free-flying crafts: seeded MJCFs of one body on a free joint with rotors, drawn
over the ranges of descriptions a user could bring (docs/flyers.md), beside the pivoted families of
:mod:`envs.families`.

``flyer_scene(seed)`` returns ``(mjcf_text, facts)``; everything comes from
``numpy.random.default_rng(seed)``, so a seed is a craft. :func:`write_flyers` writes
``flyer_<seed>.xml`` (and the facts beside it as JSON) that any command takes as ``--scene PATH``.

What a draw is (:data:`FLYER_RANGES`):

* mass 0.02–5 kg (log-uniform), arms ``0.17 m · (m / 0.5 kg)^(1/3)`` times 0.8–1.25 (a 27 g craft
  gets 5–8 cm, a 5 kg one 30–45 cm);
* the inertia from geoms (MuJoCo's ``inertiafromgeom``): a hub box, one capsule arm and one motor
  cylinder per rotor, and a payload box placed so that the centre of mass is up to a third of the
  arm length off the body origin; the principal frame is wherever the geoms put it (rotated);
* 4, 6 or 8 rotors, on a regular frame (equal angles, equal arms) or an irregular one (angles
  jittered by up to 15°, arms by 0.8–1.2); each at its own height (up to ±15 % of the arm), spins
  alternating around the frame; all tilted by one angle up to 5° about their arms, the way that adds
  to the yaw reaction (a third of the draws: not tilted);
* actuation (three quarters of the draws): a site ``motor`` per rotor whose gear carries the thrust
  and the yaw reaction ``κ = 0.05–0.12`` arm lengths, ``ctrlrange`` 0 to a share of the
  thrust-to-weight; or, as many descriptions do, one thrust site at the body origin and three
  body-moment actuators (site gears ``(0 0 0 1 0 0)`` …), moment bounds as a rotor frame would give;
* thrust-to-weight 1.5–4, optional fluid drag (half the draws: air, ``density`` 1.2,
  ``viscosity`` 1.8e-5), timestep 1–10 ms (0.1 ms grid), integrator RK4 or implicitfast, no floor,
  no contact.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Iterable

import mujoco
import numpy as np

from fvin_mpc.core import s3

#: The ranges of a draw (see the module docstring).
FLYER_RANGES: dict[str, Any] = {
    "mass_kg": (0.02, 5.0),
    "arm_factor": (0.8, 1.25),
    "rotors": (4, 6, 8),
    "irregular_angle_deg": 15.0,
    "irregular_arm": (0.8, 1.2),
    "height_fraction": 0.15,
    "tilt_deg": 5.0,
    "com_offset_arm_fraction": 1.0 / 3.0,
    "yaw_coefficient_arm_fraction": (0.05, 0.12),
    "thrust_to_weight": (1.5, 4.0),
    "wrench_share": 0.25,
    "drag_share": 0.5,
    "timestep_ms": (1.0, 10.0),
    "integrators": ("RK4", "implicitfast"),
}

_NO_CONTACT = 'contype="0" conaffinity="0"'


def _vector(values: Iterable[float]) -> str:
    return " ".join(f"{v:.6g}" for v in values)


def _quat_z_to(axis: np.ndarray) -> np.ndarray:
    """The shortest rotation taking ``e_z`` to the unit ``axis``, ``(w, x, y, z)``."""
    q = np.array([1.0 + axis[2], -axis[1], axis[0], 0.0])
    return q / np.linalg.norm(q)


def flyer_scene(seed: int) -> tuple[str, dict[str, Any]]:
    """The craft of ``seed``: ``(mjcf_text, facts)`` (module docstring)."""
    r = FLYER_RANGES
    rng = np.random.default_rng(seed)
    mass = math.exp(rng.uniform(*np.log(r["mass_kg"])))
    arm = 0.17 * (mass / 0.5) ** (1.0 / 3.0) * rng.uniform(*r["arm_factor"])
    rotors = int(rng.choice(r["rotors"]))
    regular = bool(rng.uniform() < 0.5)
    angles = (np.arange(rotors) + 0.5) * 2.0 * math.pi / rotors
    arms = np.full(rotors, arm)
    if not regular:
        angles = angles + np.radians(rng.uniform(-1.0, 1.0, rotors) * r["irregular_angle_deg"])
        arms = arm * rng.uniform(*r["irregular_arm"], size=rotors)
    heights = arm * rng.uniform(-1.0, 1.0, rotors) * r["height_fraction"]
    spins = np.where(np.arange(rotors) % 2 == 0, 1.0, -1.0)
    # tilted as real frames are: every rotor by one angle about its arm, towards the side where the
    # tilt's yaw torque adds to the rotor's reaction (so the tilts' lateral forces cancel on a regular frame)
    tilt = 0.0 if rng.uniform() < 1.0 / 3.0 else rng.uniform(0.0, r["tilt_deg"])
    tangents = np.column_stack([-np.sin(angles), np.cos(angles), np.zeros(rotors)])
    axes = [math.cos(math.radians(tilt)) * np.array([0.0, 0.0, 1.0]) - math.sin(math.radians(tilt)) * s * t
            for s, t in zip(spins, tangents)]
    kappa = arm * rng.uniform(*r["yaw_coefficient_arm_fraction"])
    thrust_to_weight = rng.uniform(*r["thrust_to_weight"])
    wrench = bool(rng.uniform() < r["wrench_share"])
    drag = bool(rng.uniform() < r["drag_share"])
    timestep = round(round(rng.uniform(*r["timestep_ms"]), 1) * 1e-3, 4)
    integrator = str(rng.choice(r["integrators"]))

    # mass shares: hub, arms and motors, payload (the payload moves the centre of mass)
    payload_share = rng.uniform(0.15, 0.35)
    hub_share = rng.uniform(0.3, 0.5) * (1.0 - payload_share)
    rotor_mass = (1.0 - payload_share - hub_share) * mass / rotors
    offset_direction = rng.normal(size=3)
    offset_direction /= np.linalg.norm(offset_direction)
    offset = offset_direction * arm * rng.uniform(0.0, r["com_offset_arm_fraction"])
    hub = np.array([0.3, 0.2, 0.08]) * arm * rng.uniform(0.8, 1.2, 3)
    positions = np.column_stack([arms * np.cos(angles), arms * np.sin(angles), heights])
    # the payload sits where it puts the whole centre of mass at ``offset`` from the body origin
    # (an arm's mass sits at its midpoint, a motor's at the rotor: 0.4·½ + 0.6 of each rotor's mass at its site)
    payload_at = (mass * offset - 0.8 * rotor_mass * positions.sum(axis=0)) / (payload_share * mass)
    payload_size = 0.5 * hub

    geoms = [f'<geom name="hub" type="box" size="{_vector(hub)}" mass="{hub_share * mass:.6g}" {_NO_CONTACT}/>',
             f'<geom name="payload" type="box" pos="{_vector(payload_at)}" size="{_vector(payload_size)}" '
             f'mass="{payload_share * mass:.6g}" {_NO_CONTACT}/>']
    sites, actuators = [], []
    for i, (p, axis) in enumerate(zip(positions, axes)):
        geoms.append(f'<geom name="arm{i}" type="capsule" fromto="0 0 0 {_vector(p)}" size="{0.04 * arm:.6g}" '
                     f'mass="{0.4 * rotor_mass:.6g}" {_NO_CONTACT}/>')
        geoms.append(f'<geom name="motor{i}" type="cylinder" pos="{_vector(p)}" '
                     f'size="{0.3 * arm:.6g} {0.02 * arm:.6g}" quat="{_vector(_quat_z_to(axis))}" '
                     f'mass="{0.6 * rotor_mass:.6g}" {_NO_CONTACT}/>')
    weight = mass * 9.81
    if wrench:
        sites.append('<site name="thrust" pos="0 0 0"/>')
        # the moments a rotor frame of the same size would give (half the thrust range at the arm, κ for yaw)
        roll_pitch, yaw = 0.5 * arm * thrust_to_weight * weight / 2.0, kappa * thrust_to_weight * weight / 2.0
        actuators.append(f'<motor name="thrust" site="thrust" gear="0 0 1 0 0 0" '
                         f'ctrlrange="0 {thrust_to_weight * weight:.6g}"/>')
        for name, gear, bound in (("roll", "0 0 0 1 0 0", roll_pitch), ("pitch", "0 0 0 0 1 0", roll_pitch),
                                  ("yaw", "0 0 0 0 0 1", yaw)):
            actuators.append(f'<motor name="{name}" site="thrust" gear="{gear}" ctrlrange="{-bound:.6g} {bound:.6g}"/>')
    else:
        for i, (p, axis, spin) in enumerate(zip(positions, axes, spins)):
            sites.append(f'<site name="rotor{i}" pos="{_vector(p)}" quat="{_vector(_quat_z_to(axis))}"/>')
            actuators.append(f'<motor name="rotor{i}" site="rotor{i}" gear="0 0 1 0 0 {spin * kappa:.6g}" '
                             f'ctrlrange="0 {thrust_to_weight * weight / rotors:.6g}"/>')
    fluid = ' density="1.2" viscosity="1.8e-5"' if drag else ""
    body = "\n      ".join(["<freejoint/>", *geoms, *sites])
    mjcf = f"""<mujoco model="flyer_{seed}">
  <compiler angle="radian" inertiafromgeom="true"/>
  <option timestep="{timestep:.4g}" integrator="{integrator}" gravity="0 0 -9.81"{fluid}>
    <flag contact="disable"/>
  </option>
  <worldbody>
    <light pos="0 -3 5" dir="0 1 -1.5"/>
    <body name="flyer" pos="0 0 1">
      {body}
    </body>
  </worldbody>
  <actuator>
    {chr(10).join('    ' + a for a in actuators).strip()}
  </actuator>
</mujoco>
"""
    model = mujoco.MjModel.from_xml_string(mjcf)
    facts = {
        "seed": seed, "mass_kg": float(model.body_subtreemass[1]), "arm_m": arm, "rotors": rotors,
        "regular_frame": regular, "max_tilt_deg": tilt, "actuation": "wrench" if wrench else "rotors",
        "actuators": int(model.nu), "yaw_coefficient_m": kappa, "thrust_to_weight": thrust_to_weight,
        "fluid_drag": drag, "timestep_s": timestep, "integrator": integrator,
        "com_offset_m": float(np.linalg.norm(model.body_ipos[1])),
        "com_offset_arm_fraction": float(np.linalg.norm(model.body_ipos[1]) / arm),
        "inertia_kgm2": [float(v) for v in model.body_inertia[1]],
        "inertial_frame_rotation_deg": float(np.degrees(s3.geodesic_angles(model.body_iquat[1], (1.0, 0.0, 0.0, 0.0)))),
    }
    return mjcf, facts


def write_flyers(seeds: Iterable[int], directory: str | Path) -> list[Path]:
    """``flyer_<seed>.xml`` and ``flyer_<seed>.json`` (the facts) in ``directory``; the MJCF paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for seed in seeds:
        mjcf, facts = flyer_scene(int(seed))
        path = directory / f"flyer_{seed}.xml"
        path.write_text(mjcf)
        path.with_suffix(".json").write_text(json.dumps(facts, indent=1) + "\n")
        paths.append(path)
    return paths

"""Scene registry and physics declarations: simulate only the effects a scene calls for.

A scene is an MJCF file plus a :class:`SceneSpec` naming the observed body, the control
period, the goal orientation and a :class:`ScenePhysics` declaration of the physical
effects it needs. :func:`build_model` compiles the MJCF and switches off, through
``model.opt.disableflags``, every effect the declaration does not call for.

Policy for declaration vs. MJCF (one rule per direction):

* **Declared off, present in the MJCF** — switched off. This is the point of the
  declaration (e.g. the same MJCF without gravity or damping); no error.
* **Declared on, absent from the MJCF** — ``ValueError``. Nothing can be switched on that
  the file does not contain (zero gravity vector, no joint with ``damping > 0``, ...), so
  the declaration would be a false statement about the simulation.
* **Effects the declaration has no word for** (joint springs, joint limits, equality
  constraints, tendons) are always switched off; if the MJCF contains one, ``ValueError``
  rather than silently simulating something else than the file says.

For a user MJCF, :func:`infer_physics` reads the declaration off the file (as the file would
simulate it, including its own ``<flag>`` settings); callers override fields with
``dataclasses.replace(infer_physics(model), ...)``. Built-in scenes declare ``contact=False``.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from fvin_mpc.core.errors import SceneError
from fvin_mpc.core.goals import GoalSet, default_goal_set
from fvin_mpc.core.space import R3S3, S3, ConfigurationSpace

SCENE_DIR = Path(__file__).resolve().parent / "scenes"

_DSBL = mujoco.mjtDisableBit

#: Disable flags of effects :class:`ScenePhysics` has no field for; always set.
ALWAYS_DISABLED = int(_DSBL.mjDSBL_SPRING | _DSBL.mjDSBL_LIMIT | _DSBL.mjDSBL_EQUALITY)


@dataclass(frozen=True)
class ScenePhysics:
    """The physical effects a scene calls for; everything else is switched off.

    Attributes:
        gravity: gravity acts (``mjDSBL_GRAVITY`` cleared).
        joint_damping: joint damping acts (``mjDSBL_DAMPER`` cleared).
        dry_friction: joint friction loss acts (``mjDSBL_FRICTIONLOSS`` cleared).
        actuator_limits: controls are clamped to the actuators' ``ctrlrange``
            (``mjDSBL_CLAMPCTRL`` cleared) and the env's action space is bounded by it.
        contact: collisions are detected and resolved (``mjDSBL_CONTACT`` cleared).
        sensor_noise_std: standard deviation of Gaussian noise added to each of the 7
            observation entries (the quaternion is then renormalized); 0 draws nothing.
        gyro_noise_std: standard deviation (rad/s) of Gaussian noise added to the observed angular
            velocity only (a rate gyro); 0 draws nothing.
        gyro_axes: ``"body"``: a three-axis gyro, noise on every body-frame rate (about axes the joint
            cannot turn too); ``"joint"``: a gyro on the joint's axis, noise on the rate about a hinge's
            axis only (a ball joint turns about every axis: the same as ``"body"``).
        encoder_bits: the hinge angle is observed through an absolute encoder of this many bits per
            turn (the joint angle rounded to a multiple of ``2π / 2**bits``; the quaternion is the
            rounded angle's); ``None``: exact. A hinge's effect only.
        actuation_delay_s: the torque reaches the joint this long after it is commanded (rounded up
            to whole MuJoCo timesteps; zero torque before the first one arrives): a delay nothing in
            the observation reveals.
        mass_scale: every body's mass and rotational inertia are this multiple of the MJCF's (a
            denser or lighter body of the same shape; 1: as written).
        impulse_delta_omega: once per episode, after the body has stayed within
            :data:`IMPULSE_HOLD_TOLERANCE` of its goal for :data:`IMPULSE_HOLD_S`, its angular velocity
            jumps by this much (rad/s; a hinge: about its axis, the sign drawn from the env's
            ``np_random``; a ball: in a drawn direction) — a knock while holding. 0: never.
        impulse_at_s: the knock comes at the first (partial) control period that starts at or after this
            time of an episode instead (whether held or not); ``None``: after the hold above.
        mass_change: ``(time_s, scale)``: from the first (partial) control period that starts at or after
            ``time_s`` of an episode on, every body's mass and rotational inertia are ``scale`` times what
            they were at reset (a bob that doubles while held, a payload picked up), and what MuJoCo derives
            from them recomputed; ``reset`` restores them. ``(time_s, scale, shift)``: every body's centre of
            mass also moves by ``shift`` (m, in its own frame) — a payload hung off-centre. Nothing in the
            observation announces it. ``None``: the plant never changes.
        actuator_change: ``(time_s, index, scale)``: from the first (partial) control period that starts at or
            after ``time_s`` on, actuator ``index`` delivers ``scale`` times what it is commanded (its gear
            scaled: a worn rotor's thrust and its yaw reaction alike); ``reset`` restores it; unannounced.
            ``None``: the actuators never change.
    """

    gravity: bool
    joint_damping: bool
    dry_friction: bool
    actuator_limits: bool
    contact: bool
    sensor_noise_std: float = 0.0
    gyro_noise_std: float = 0.0
    gyro_axes: str = "body"
    encoder_bits: int | None = None
    actuation_delay_s: float = 0.0
    mass_scale: float = 1.0
    impulse_delta_omega: float = 0.0
    impulse_at_s: float | None = None
    mass_change: tuple[Any, ...] | None = None
    actuator_change: tuple[float, int, float] | None = None

    def __post_init__(self) -> None:
        for name in ("sensor_noise_std", "gyro_noise_std", "actuation_delay_s", "impulse_delta_omega"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        if self.gyro_axes not in ("body", "joint"):
            raise ValueError(f"gyro_axes must be 'body' or 'joint', got {self.gyro_axes!r}")
        if not (math.isfinite(self.mass_scale) and self.mass_scale > 0.0):
            raise ValueError(f"mass_scale must be finite and > 0, got {self.mass_scale!r}")
        if self.impulse_at_s is not None and not (math.isfinite(self.impulse_at_s) and self.impulse_at_s >= 0.0):
            raise ValueError(f"impulse_at_s must be None or finite seconds >= 0, got {self.impulse_at_s!r}")
        if self.mass_change is not None:
            change = tuple(self.mass_change)
            shift = np.asarray(change[2], dtype=float) if len(change) == 3 else np.zeros(3)
            if not (len(change) in (2, 3) and shift.shape == (3,) and np.all(np.isfinite(shift))
                    and all(math.isfinite(float(v)) for v in change[:2])
                    and float(change[0]) >= 0.0 and float(change[1]) > 0.0):
                raise ValueError(f"mass_change must be (time_s >= 0, scale > 0) or (time_s, scale, centre-of-mass "
                                 f"shift (3,) m), got {self.mass_change!r}")
            normal = (float(change[0]), float(change[1]))
            object.__setattr__(self, "mass_change", normal + ((tuple(map(float, shift)),) if len(change) == 3 else ()))
        if self.actuator_change is not None:
            at, index, scale = self.actuator_change
            if not (math.isfinite(float(at)) and float(at) >= 0.0 and int(index) == index and int(index) >= 0
                    and math.isfinite(float(scale)) and float(scale) >= 0.0):
                raise ValueError(f"actuator_change must be (time_s >= 0, actuator index >= 0, scale >= 0), "
                                 f"got {self.actuator_change!r}")
            object.__setattr__(self, "actuator_change", (float(at), int(index), float(scale)))
        if self.encoder_bits is not None and not (isinstance(self.encoder_bits, int) and 1 <= self.encoder_bits <= 32):
            raise ValueError(f"encoder_bits must be None or an integer in [1, 32], got {self.encoder_bits!r}")

    def disable_flags(self) -> int:
        """The ``mjtDisableBit`` mask that switches off everything not declared."""
        flags = ALWAYS_DISABLED
        for declared, bit in (
            (self.gravity, _DSBL.mjDSBL_GRAVITY),
            (self.joint_damping, _DSBL.mjDSBL_DAMPER),
            (self.dry_friction, _DSBL.mjDSBL_FRICTIONLOSS),
            (self.actuator_limits, _DSBL.mjDSBL_CLAMPCTRL),
            (self.contact, _DSBL.mjDSBL_CONTACT),
        ):
            if not declared:
                flags |= int(bit)
        return flags


@dataclass(frozen=True)
class SceneSpec:
    """A scene: its MJCF, its physics, the observed body and the task — one declaration.

    Only ``name`` and ``xml_path`` are required; every other field left at ``None`` is read off
    the MJCF by :class:`~fvin_mpc.envs.RigidBodyEnv` (so a user's MJCF path is the declaration
    ``SceneSpec(name=<file stem>, xml_path=<path>)``, treated exactly like a built-in scene).

    Attributes:
        name: registry key, e.g. ``"pendulum"``; for an MJCF path, the file's stem.
        xml_path: the MJCF file.
        body: name of the observed body; ``None``: the MJCF's only body with a joint.
        control_period: seconds per env step, a whole multiple of the MJCF timestep; ``None``:
            chosen from the scene's speed scale (``envs.rigid_body_env.scale_control_period``),
            at least :data:`MIN_CONTROL_PERIOD`.
        physics: the effects simulated (see :class:`ScenePhysics`); ``None``: what the MJCF
            would simulate (:func:`infer_physics`).
        goal: goal orientation ``(w, x, y, z)``; ``None``: the maximum of the potential.
        rest: the orientation of the potential's minimum (hanging), where episodes start and
            which sets the energy scale of the controllers; ``None``: read off the potential.
        checkpoint: the default model; ``None``: ``<name>_sign-invariant``, which is also where
            ``python -m fvin_mpc.train`` writes a model of this scene by default.
        space: the configuration space of the observed body's state (:mod:`fvin_mpc.core.space`):
            S³ for a body on a hinge or ball joint, R³ × S³ for a free body.
        goal_set: what counts as the goal (:mod:`fvin_mpc.core.goals`): a pivot's upright orientation at
            rest, a craft's hover point; ``None``: :func:`~fvin_mpc.core.goals.default_goal_set` of the
            space's blocks (a free joint hovers).
    """

    name: str
    xml_path: Path
    body: str | None = None
    control_period: float | None = None
    physics: ScenePhysics | None = None
    goal: tuple[float, float, float, float] | None = None
    rest: tuple[float, float, float, float] | None = None
    checkpoint: str | None = None
    space: ConfigurationSpace = S3
    goal_set: GoalSet | None = None

    def __post_init__(self) -> None:
        if self.goal_set is None:
            object.__setattr__(self, "goal_set", default_goal_set(self.space.layout))

    @property
    def default_checkpoint(self) -> str:
        """The checkpoint the CLIs use for this scene when none is given."""
        return self.checkpoint or f"{self.name}_sign-invariant"


#: A knock (``ScenePhysics.impulse_delta_omega``) comes once the body has stayed this close to its goal
#: (rad; the controllers' "upright") …
IMPULSE_HOLD_TOLERANCE = 0.1
#: … for this long (s).
IMPULSE_HOLD_S = 1.0

#: The shortest control period (s) of a scene that declares none: its period follows its speed scale
#: but never drops below this, whatever the MJCF's timestep (an MPC solve must fit in a period).
MIN_CONTROL_PERIOD = 0.02

_ACTUATED = ScenePhysics(gravity=True, joint_damping=False, dry_friction=False, actuator_limits=True, contact=False)

def _built_in(name: str, physics: ScenePhysics) -> SceneSpec:
    """A scene of ``envs/scenes/<name>.xml``: the built-in MJCFs all observe the body ``pendulum``
    and are controlled at 50 ms (ten RK4 steps of 5 ms)."""
    return SceneSpec(name=name, xml_path=SCENE_DIR / f"{name}.xml", body="pendulum", control_period=0.05,
                     physics=physics)


SCENES: dict[str, SceneSpec] = {
    spec.name: spec
    for spec in (
        _built_in("pendulum", _ACTUATED),
        _built_in("pendulum_damped", replace(_ACTUATED, joint_damping=True)),
        _built_in("spherical_pendulum", _ACTUATED),
    )
}
# How to control them (horizons, solver settings, each with its reason) is control's business:
# fvin_mpc/control/presets.py.


#: Scenes of one free body (a 13-number state ``(x, q, v, ω)``, :class:`~fvin_mpc.envs.QuadrotorEnv`),
#: apart from :data:`SCENES` (bodies on a pivot, :class:`~fvin_mpc.envs.RigidBodyEnv`), whose
#: consumers build a pivoted env from every entry. :func:`get_scene` and :func:`resolve_scene` know both.
FREE_BODY_SCENES: dict[str, SceneSpec] = {
    # 20 ms (50 Hz, ten RK4 sub-steps of 2 ms): the craft's attitude is fast — full differential thrust
    # turns it at ≈ 260 rad/s² about x, a tumble recovers within a few tenths of a second — so 50 ms
    # would leave the MPC two or three decisions per recovery; at 20 ms a tumble at |ω| = 10 rad/s
    # turns 0.2 rad per step (h|ω| = 0.2, far inside the step's solvability limit h|ω| ≈ 1), and the
    # 2 ms sub-steps let the latency-aware loop apply a torque 2 ms after it is computed.
    spec.name: spec
    for spec in (
        SceneSpec(name="quadrotor", xml_path=SCENE_DIR / "quadrotor.xml", body="quadrotor", control_period=0.02,
                  physics=_ACTUATED, goal=(1.0, 0.0, 0.0, 0.0), rest=(1.0, 0.0, 0.0, 0.0),
                  checkpoint="quadrotor_fixed-inertia", space=R3S3),
    )
}


def _all_scenes() -> dict[str, SceneSpec]:
    return {**SCENES, **FREE_BODY_SCENES}


def built_in_scene(spec: SceneSpec) -> bool:
    """Whether ``spec`` is one of the built-in declarations (not a user's scene of the same name)."""
    return _all_scenes().get(spec.name) is spec


def get_scene(name: str) -> SceneSpec:
    """The built-in :class:`SceneSpec` called ``name``; ``SceneError`` (a ``ValueError``) listing the known ones."""
    try:
        return _all_scenes()[name]
    except KeyError:
        raise SceneError(
            f"unknown scene {name!r}: expected one of {sorted(_all_scenes())} or a path to an existing MJCF (.xml) "
            "file (or, with pip install 'fvin_mpc[menagerie]', a MuJoCo Menagerie robot's name)"
        ) from None


def menagerie_mjcf(name: str) -> Path | None:
    """The MJCF of the MuJoCo Menagerie robot ``name`` (its default model, the robot without the
    scene's floor: the flyers' simulator has none), fetched on first use by the optional package
    ``mujoco-menagerie`` (``pip install 'fvin_mpc[menagerie]'``; ``MENAGERIE_ROOT`` points it at a
    local checkout); ``None`` when the package is not installed.

    Raises:
        SceneError: the package knows no such robot, or could not fetch it (the reason in one line).
    """
    try:
        import mujoco_menagerie
    except ImportError:
        return None
    if name not in mujoco_menagerie.names():
        raise SceneError(f"unknown scene {name!r}: expected one of {sorted(_all_scenes())}, a path to an existing "
                         f"MJCF (.xml) file or a MuJoCo Menagerie robot (python -m mujoco_menagerie lists them)")
    robot = mujoco_menagerie.get(name)
    try:
        return Path(robot.xml(robot.default_model))
    except Exception as error:  # the package's download and cache errors: the reason, in one line
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise SceneError(f"Menagerie robot {name!r} could not be fetched: {reason}") from None


def resolve_scene(scene: str | Path | SceneSpec) -> SceneSpec:
    """The declaration of a built-in scene name, an MJCF path, a MuJoCo Menagerie robot's name (with the
    optional package, :func:`menagerie_mjcf`) or a :class:`SceneSpec` itself.

    A path to a built-in scene's MJCF gives that scene (its settings included); any other path
    gives ``SceneSpec(name=<stem>, xml_path=<path>)``, whose fields are read off the file — its
    configuration space too: R³ × S³ when the MJCF's body hangs on a free joint, else S³. A
    Menagerie robot is its MJCF under the robot's name.

    Raises:
        ValueError: neither a built-in name nor something that looks like a path.
    """
    if isinstance(scene, SceneSpec):
        return scene
    if isinstance(scene, str) and scene in _all_scenes():
        return _all_scenes()[scene]
    path = Path(scene)
    if isinstance(scene, Path) or path.suffix.lower() == ".xml" or path.exists():
        for spec in _all_scenes().values():
            if path.exists() and path.resolve() == spec.xml_path.resolve():
                return spec
        return SceneSpec(name=path.stem, xml_path=path, space=_space_of_mjcf(path))
    menagerie = menagerie_mjcf(str(scene))
    if menagerie is not None:
        return SceneSpec(name=str(scene), xml_path=menagerie, space=_space_of_mjcf(menagerie))
    return get_scene(str(scene))


def _space_of_mjcf(path: Path) -> ConfigurationSpace:
    """The configuration space of the body an MJCF file describes: a free joint makes it a free body.
    A file that is missing or does not load is S³ here: :func:`build_model` reports it."""
    try:
        model, _ = _compiled(path)
    except (ValueError, OSError):
        return S3
    return R3S3 if np.any(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE) else S3
def existing_scene(scene: str | Path | SceneSpec) -> SceneSpec:
    """:func:`resolve_scene`, refusing at once a scene whose MJCF file is not there.

    A command checks its ``--scene`` with this before anything else: a misspelt name or path must
    be reported as such, not as the missing checkpoint its name would have led to.

    Raises:
        SceneError: an unknown name, or a path to no file; the message lists the built-in scenes.
    """
    spec = resolve_scene(scene)
    if not spec.xml_path.is_file():
        raise SceneError(f"scene file does not exist: {str(spec.xml_path)!r}; expected one of the built-in scenes "
                         f"{sorted(_all_scenes())} or a path to an existing MJCF (.xml) file")
    model, physics = build_model(spec.xml_path, spec.physics)  # the MJCF's physics, checked (check_physics)
    check_bounded_controls(model, physics, spec.name)
    return spec


def check_bounded_controls(model: mujoco.MjModel, physics: ScenePhysics, name: str) -> None:
    """``SceneError`` unless every actuator's control is clamped to a finite ``ctrlrange``: the commands'
    controllers plan within the bounds, and the data collectors draw controls from them (an env itself
    may run unbounded, :class:`~fvin_mpc.envs.RigidBodyEnv`, but nothing a command runs can)."""
    unbounded = [_actuator_name(model, a) for a in range(model.nu)
                 if not (physics.actuator_limits and model.actuator_ctrllimited[a])]
    if unbounded:
        off = (" (control clamping is switched off: <flag clampctrl> or the declaration)"
               if np.any(model.actuator_ctrllimited) and not physics.actuator_limits else "")
        raise SceneError(f"scene {name!r}: actuator {unbounded[0]!r} has no control bounds{off}; the controllers and "
                         'data collectors need them: give every actuator a finite ctrlrange="low high"')


#: A gear no component of which is this large is zero: the actuator delivers nothing.
_NONZERO = 1e-12


def _numbers(values: Any) -> str:
    return "[" + ", ".join(f"{float(v):g}" for v in np.ravel(values)) + "]"


def _actuator_name(model: mujoco.MjModel, index: int) -> str:
    return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, index) or f"#{index}"


def check_physics(model: mujoco.MjModel, name: str) -> None:
    """Refuse, before any work, an MJCF whose physics no simulation or model of the package can take
    (``SceneError``, one line naming the element and what to change):

    * a timestep that is not a finite number of seconds above zero (MuJoCo accepts 0, and a 0 s step
      divides every period by zero);
    * gravity, a body's mass or its inertia that is not finite, or a moving body without mass;
    * an actuator whose gear is not finite or is zero (a motor that delivers nothing, whatever its
      control), whose ``ctrlrange`` is not finite, or whose kind the package does not model: a control
      with internal state (``dyntype``), a bias (a position or velocity servo: its force depends on the
      state, not on the control alone) or a gain that is not fixed — every model here takes a control as
      a force or torque, gear times control.

    What a scale decides — whether the timestep resolves the body's speed, whether the motor can move
    the body, whether a craft can hover — needs the body read off the file and is the envs' check
    (:class:`~fvin_mpc.envs.RigidBodyEnv`, :class:`~fvin_mpc.envs.QuadrotorEnv`).
    """
    where = f"scene {name!r}"
    timestep = float(model.opt.timestep)
    if not (math.isfinite(timestep) and timestep > 0.0):
        raise SceneError(f"{where}: the MJCF's timestep must be a finite number of seconds > 0, got {timestep:g} "
                         '(<option timestep="0.005"/>, say)')
    if not np.all(np.isfinite(model.opt.gravity)):
        raise SceneError(f"{where}: gravity must be finite, got {_numbers(model.opt.gravity)}")
    for body in range(1, model.nbody):
        body_name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or f"#{body}"
        mass, inertia = float(model.body_mass[body]), model.body_inertia[body]
        if not (math.isfinite(mass) and mass >= 0.0 and np.all(np.isfinite(inertia)) and np.all(inertia >= 0.0)):
            raise SceneError(f"{where}: body {body_name!r} has mass {mass:g} kg and inertia {_numbers(inertia)}; "
                             "both must be finite and >= 0")
    none_dyn, none_bias = int(mujoco.mjtDyn.mjDYN_NONE), int(mujoco.mjtBias.mjBIAS_NONE)
    for a in range(model.nu):
        actuator = f"{where}: actuator {_actuator_name(model, a)!r}"
        gear = np.asarray(model.actuator_gear[a], dtype=float)
        if not np.all(np.isfinite(gear)):
            raise SceneError(f"{actuator} has gear {_numbers(gear)}: it must be finite")
        if float(np.abs(gear).max()) < _NONZERO:
            raise SceneError(f"{actuator} has gear 0: it delivers no force or torque whatever its control; give it "
                             'a nonzero gear (gear="1": the control is the torque)')
        if model.actuator_ctrllimited[a] and not np.all(np.isfinite(model.actuator_ctrlrange[a])):
            raise SceneError(f"{actuator} has ctrlrange {_numbers(model.actuator_ctrlrange[a])}: a bound must be "
                             'finite (ctrlrange="-2 2", say)')
        if int(model.actuator_dyntype[a]) != none_dyn:
            raise SceneError(f"{actuator} has dynamics (dyntype {mujoco.mjtDyn(int(model.actuator_dyntype[a])).name}):"
                             " the package models actuators without internal state; use a <motor>")
        if int(model.actuator_biastype[a]) != none_bias:
            raise SceneError(f"{actuator} has a bias (a <position> or <velocity> servo, biastype "
                             f"{mujoco.mjtBias(int(model.actuator_biastype[a])).name}): the package models force and "
                             "torque motors, whose force is gear × control; use a <motor>")
        if int(model.actuator_gaintype[a]) != int(mujoco.mjtGain.mjGAIN_FIXED):
            raise SceneError(f"{actuator} has a gain of type {mujoco.mjtGain(int(model.actuator_gaintype[a])).name}: "
                             "the package models a fixed gain (force = gear × control); use a <motor>")


def _disabled(model: mujoco.MjModel, bit: int) -> bool:
    return bool(model.opt.disableflags & int(bit))


def can_collide(model: mujoco.MjModel) -> bool:
    """Whether any geom pair could ever produce a contact (explicit ``<pair>`` or contype/conaffinity).

    Follows MuJoCo's filters: geoms of one weld group never collide, nor do geoms of a
    parent and child body (unless the parent is the world or ``filterparent`` is disabled).
    Excluded body pairs (``<exclude>``) are ignored, so the answer errs towards ``True``.
    """
    if model.npair > 0:
        return True
    filter_parent = not _disabled(model, _DSBL.mjDSBL_FILTERPARENT)
    weld_of_geom = model.body_weldid[model.geom_bodyid]
    weld_parent = model.body_weldid[model.body_parentid]
    for i in range(model.ngeom):
        for j in range(i + 1, model.ngeom):
            weld_i, weld_j = int(weld_of_geom[i]), int(weld_of_geom[j])
            if weld_i == weld_j:
                continue
            parent_child = weld_i == weld_parent[weld_j] or weld_j == weld_parent[weld_i]
            if filter_parent and parent_child and weld_i != 0 and weld_j != 0:
                continue
            contype, conaffinity = model.geom_contype, model.geom_conaffinity
            if (contype[i] & conaffinity[j]) or (contype[j] & conaffinity[i]):
                return True
    return False


def present_effects(model: mujoco.MjModel) -> dict[str, bool]:
    """Which declarable effects the compiled MJCF contains, ignoring its disable flags."""
    return {
        "gravity": bool(np.linalg.norm(model.opt.gravity) > 0.0),
        "joint_damping": bool(np.any(model.dof_damping > 0.0)),
        "dry_friction": bool(np.any(model.dof_frictionloss > 0.0)),
        "actuator_limits": bool(np.any(model.actuator_ctrllimited)),
        "contact": can_collide(model),
    }


def infer_physics(model: mujoco.MjModel) -> ScenePhysics:
    """The declaration a user MJCF implies: each effect present and not disabled by the file's own flags."""
    present = present_effects(model)
    own_flag = {
        "gravity": _DSBL.mjDSBL_GRAVITY,
        "joint_damping": _DSBL.mjDSBL_DAMPER,
        "dry_friction": _DSBL.mjDSBL_FRICTIONLOSS,
        "actuator_limits": _DSBL.mjDSBL_CLAMPCTRL,
        "contact": _DSBL.mjDSBL_CONTACT,
    }
    return ScenePhysics(**{name: present[name] and not _disabled(model, bit) for name, bit in own_flag.items()})


def check_unsupported_effects(model: mujoco.MjModel) -> None:
    """``ValueError`` if the MJCF contains an effect :class:`ScenePhysics` cannot declare."""
    problems = []
    if np.any(model.jnt_stiffness != 0.0):
        problems.append("joint springs (stiffness != 0)")
    if np.any(model.jnt_limited):
        problems.append("joint limits (limited joints)")
    if model.neq > 0:
        problems.append("equality constraints")
    if model.ntendon > 0:
        problems.append("tendons")
    if problems:
        raise SceneError(
            "the MJCF contains effects the scene physics declaration has no field for and that would be "
            f"switched off: {', '.join(problems)}; remove them from the file"
        )


def apply_physics(model: mujoco.MjModel, physics: ScenePhysics) -> None:
    """Set ``model.opt.disableflags`` from ``physics`` (in place), after checking it against the MJCF.

    Raises:
        ValueError: an effect is declared on but absent from the MJCF, or the MJCF contains
            an effect no declaration covers (see the module docstring for the policy).
    """
    check_unsupported_effects(model)
    present = present_effects(model)
    missing = [name for name, is_present in present.items() if getattr(physics, name) and not is_present]
    if missing:
        raise SceneError(
            f"physics declares {missing} but the MJCF contains no such effect "
            "(gravity vector zero / no dof damping / no frictionloss / no ctrllimited actuator / "
            "no geom pair that can collide); declare it off or add it to the MJCF"
        )
    managed = ALWAYS_DISABLED | int(
        _DSBL.mjDSBL_GRAVITY | _DSBL.mjDSBL_DAMPER | _DSBL.mjDSBL_FRICTIONLOSS
        | _DSBL.mjDSBL_CLAMPCTRL | _DSBL.mjDSBL_CONTACT
    )
    model.opt.disableflags = (int(model.opt.disableflags) & ~managed) | physics.disable_flags()


def _compiled(path: Path) -> tuple[mujoco.MjModel, list[str]]:
    """``path`` compiled, and the warnings MuJoCo raised meanwhile: collected rather than printed (MuJoCo's
    own handler prints them and writes ``MUJOCO_LOG.TXT`` into the working directory)."""
    warnings: list[str] = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(warnings.append)
    try:
        return mujoco.MjModel.from_xml_path(str(path)), warnings
    finally:
        mujoco.set_mju_user_warning(previous)


def load_model(xml_path: str | Path) -> mujoco.MjModel:
    """Compile an MJCF file; ``SceneError`` (a ``ValueError``) naming the file if it is missing, invalid or
    holds a NaN (which MuJoCo only warns about). MuJoCo's other warnings are notes on stderr."""
    path = Path(xml_path)
    if not path.is_file():
        raise SceneError(f"MJCF file not found: {str(path)!r}")
    try:
        model, warnings = _compiled(path)
    except ValueError as error:
        raise SceneError(f"could not compile MJCF {str(path)!r}: {error}") from error
    if any("nan" in warning.lower() for warning in warnings):
        raise SceneError(f"MJCF {str(path)!r} holds a NaN where a number belongs (MuJoCo: {warnings[0].strip()}); "
                         "every value of the physics must be a finite number")
    for warning in warnings:
        print(f"note: MuJoCo, compiling {str(path)!r}: {warning.strip()}", file=sys.stderr)
    return model


def build_model(xml_path: str | Path, physics: ScenePhysics | None = None) -> tuple[mujoco.MjModel, ScenePhysics]:
    """Compile ``xml_path`` and switch off every effect not in ``physics``.

    Args:
        xml_path: MJCF file.
        physics: the declaration; ``None`` infers it from the file (:func:`infer_physics`).

    Returns:
        ``(model, physics)``: the model with ``opt.disableflags`` set (and energy
        computation enabled), and the declaration actually used.

    Raises:
        SceneError: the file is missing or does not compile, its physics is broken (:func:`check_physics`),
            or it contradicts the declaration (:func:`apply_physics`).
    """
    model = load_model(xml_path)
    check_physics(model, Path(xml_path).stem)
    if physics is None:
        physics = infer_physics(model)
    if physics.mass_change is not None and len(physics.mass_change) == 3:
        model = compiled_for_moving_centres(xml_path, model)
    apply_physics(model, physics)
    if physics.mass_scale != 1.0:
        scale_mass(model, physics.mass_scale)
    model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    return model, physics



def compiled_for_moving_centres(xml_path: str | Path, built: mujoco.MjModel) -> mujoco.MjModel:
    """``xml_path`` compiled so that a centre of mass moved in place later (``ScenePhysics.mass_change``'s shift)
    is simulated, with ``built``'s values.

    MuJoCo's compiler marks a body whose inertial frame is its own frame "simple" and gives its degrees of freedom
    a diagonal mass matrix (``dof_simplenum`` and the sparsity built for it), which ``mj_setConst`` does not
    rebuild. A free craft whose centre moved 2 cm in place then turned about its frame's origin with the
    parallel-axis inertia and never accelerated sideways: an 8 % error in its angular acceleration and none of
    the coupling of translation and rotation (tests/test_scene_physics.py). So the scene is compiled once with
    every body's inertial frame off its origin (explicit inertials), then ``built``'s values are put back in
    place: the general mass matrix simulates the centre wherever it is later moved."""
    spec = mujoco.MjSpec.from_file(str(xml_path))
    # the built values as they are: a file that computes inertias from its geoms would override them
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    bodies = list(spec.bodies)
    if len(bodies) != built.nbody:
        raise SceneError(f"{str(xml_path)!r}: its spec has {len(bodies)} bodies, the compiled model {built.nbody}")
    for index, body in enumerate(bodies[1:], start=1):
        body.explicitinertial = True
        body.mass = float(built.body_mass[index])
        body.inertia = built.body_inertia[index].copy()
        body.iquat = built.body_iquat[index].copy()
        body.ipos = built.body_ipos[index] + np.array([0.0, 0.0, 1e-3])  # any offset: not "simple"
    model = spec.compile()
    if not (np.allclose(model.body_mass, built.body_mass) and np.allclose(model.body_inertia, built.body_inertia)):
        raise SceneError(f"{str(xml_path)!r}: recompiled for a moving centre of mass, its masses or inertias changed")
    model.body_ipos[:] = built.body_ipos
    mujoco.mj_setConst(model, mujoco.MjData(model))
    return model


def scale_mass(model: mujoco.MjModel, scale: float) -> None:
    """Every body's mass and rotational inertia times ``scale`` (in place), and the constants MuJoCo derives
    from them (subtree masses, ...) recomputed: the plant changes, the file and a model read off it do not."""
    model.body_mass[1:] *= scale
    model.body_inertia[1:] *= scale
    mujoco.mj_setConst(model, mujoco.MjData(model))

"""Data that excite what a swing-up needs: energy-pumping bursts sized from the scene's own scales.

Random constant or piecewise-constant controls from random states (:func:`~fvin_mpc.learning.collection.collect`)
excite a weak actuator little against gravity: a motor of a fifth of the gravity torque, switched at
random, moves the body's energy by a few percent of the swing-up's span, so the data say little
about the damping at swing speed, the saturated motor, or the last climb to upright — the states
and controls an MPC's swing-up passes through (on the weak, damped point pendulum of docs/excitation.md a
model fitted to such data learned a dissipation 20–40 % low and its MPC never swung the body up).

:func:`collect_swings` collects instead, per trajectory, from a start drawn by one of three kinds:

* **energy spread** (:data:`SHARES` ``"energy"``): a random orientation and a speed such that the
  total energy above hanging is uniform in ``[0, 1.4·ΔE]`` (``ΔE`` the energy span between hanging
  and upright): slow and fast states at every height, upright and fast included;
* **near the goal** (``"near_goal"``): within 0.6 rad of upright, ``|ω_i| ≤ 0.5·ω_s``;
* **uniform** (``"uniform"``): the former collector's states (angle uniform, ``|ω| ≤ 1.5·ω_s``)
  under its random piecewise-constant controls.

The first two are driven by a switching policy: segments of a random dwell (1 step to a quarter of
the natural period ``2π/ω_s``), each one of pumping (every actuator at its bound in the direction of
motion: the most power the motor can put in), braking (the opposite bound), a random constant
level, or no torque (the unforced swing: the damping alone). Saturated controls, the energies of a
swing-up and the neighbourhood of the goal are all in the data.

The amount comes from the scales (:class:`SwingScales`: the env's ``energy_span`` and ``speed_scale``,
the same the control period and the control layer's ``SceneScales`` come from): every trajectory
lasts two natural periods (between :data:`MIN_STEPS` and :data:`MAX_STEPS` control periods), and there are as many
trajectories as give about :data:`TRANSITIONS` transitions.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.data import Trajectories
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.learning.collection import control_sequence, hinge_axis_record, near_goal_joint_state, random_joint_state

#: Shares of the trajectories by kind of start (module docstring).
SHARES = {"energy": 0.6, "near_goal": 0.2, "uniform": 0.2}
#: Transitions a default collection aims at (about the former default's 6,400, in longer trajectories).
TRANSITIONS = 8000
#: Bounds on the control periods per trajectory (two natural periods within them).
MIN_STEPS, MAX_STEPS = 20, 200
#: Bounds on the training window derived from the scales (:attr:`SwingScales.training_window`).
MIN_WINDOW, MAX_WINDOW = 8, 32
#: Highest energy above hanging of an energy-spread start, in units of the energy span.
MAX_ENERGY = 1.4
#: Fastest energy-spread start on a ball joint, in units of ``ω_s`` (the uniform starts' bound).
START_SPEED_CAP = 1.5
#: Energy a trajectory may gain beyond the most its actuators can put in, in units of the energy
#: span, before it counts as the simulator's divergence (legitimate trajectories of both report
#: families stay below 0.06: the integrators' own error; diverged ones reach 1–8,000).
DIVERGENCE_TOLERANCE = 0.25
#: Trajectories in a row a start may diverge on before collection gives up on the scene.
MAX_DIVERGED_IN_A_ROW = 10
#: Segment kinds of the switching policy and their probabilities.
SEGMENTS = {"pump": 0.5, "brake": 0.15, "level": 0.2, "coast": 0.15}
#: Name of the method in ``metadata["collector"]``.
SWING_EXCITATION = "swing-excitation"


@dataclass(frozen=True)
class SwingScales:
    """The scales of a scene's swing-up, read off its MJCF.

    Attributes:
        energy_span: ``|U(upright) − U(hanging)|`` (J).
        speed: ``ω_s = √(2·energy_span / J_max)`` (rad/s): the speed that carries the body over the span.
        step_size: the control period ``h`` (s).
    """

    energy_span: float
    speed: float
    step_size: float

    @property
    def natural_period(self) -> float:
        """``2π/ω_s`` (s)."""
        return 2.0 * math.pi / self.speed

    @property
    def trajectory_steps(self) -> int:
        """Control periods of a default trajectory: two natural periods, within [MIN_STEPS, MAX_STEPS]."""
        return int(min(MAX_STEPS, max(MIN_STEPS, round(2.0 * self.natural_period / self.step_size))))

    @property
    def training_window(self) -> int:
        """Rollout steps per training window: half a natural period, within [MIN_WINDOW, MAX_WINDOW].
        A window of a few steps sees the damping act for a few percent of a swing, where its effect
        on the rollout is below the fit's noise; half a swing lets a wrong damping (the damped
        point pendulum's 20–40 % low, docs/excitation.md) show as the energy it wrongly keeps."""
        return int(min(MAX_WINDOW, max(MIN_WINDOW, round(0.5 * self.natural_period / self.step_size))))

    @property
    def dwell_steps(self) -> int:
        """Longest segment of the switching policy: a quarter of the natural period, at least 1 step."""
        return max(1, round(0.25 * self.natural_period / self.step_size))


class SwingPhysics:
    """What the excitation and the swing measure need of a pivoted scene: its energy (from the
    closed-form body of the MJCF), the direction of motion each actuator pushes along, its bounds.

    Args:
        env: the scene's :class:`~fvin_mpc.envs.RigidBodyEnv` (its control period is the data's).
    """

    def __init__(self, env: Any) -> None:
        base = env.unwrapped
        self.env = env
        body = from_mujoco(base.model, base.body_name)
        self.terms = body.terms(get_ops("numpy"))
        self.center_of_mass = np.asarray(body.center_of_mass, dtype=float)
        self.low = np.asarray(base.torque_low, dtype=np.float64)
        self.high = np.asarray(base.torque_high, dtype=np.float64)
        if not (np.all(np.isfinite(self.low)) and np.all(np.isfinite(self.high))):
            raise ValueError("swing excitation needs finite actuator bounds (declare the actuators' ctrlrange, "
                             "or collect with --collector random)")
        self.rest_energy = self.potential(base.rest)
        # The env's scales are the ones its control period and the controllers' settings come from.
        self.scales = SwingScales(base.energy_span, base.speed_scale, float(base.dt))
        self.directions = actuator_directions(env)
        #: where the body's attitude and rate sit in the env's states
        self.attitude = base.space.layout.attitude(by="the swing excitation")

    def potential(self, q: Any) -> float:
        return float(self.terms.potential(tuple(float(c) for c in q)))

    def inertia(self, q: Any) -> np.ndarray:
        return np.array(self.terms.inertia(tuple(float(c) for c in q)), dtype=float)

    def energy(self, state: np.ndarray) -> float:
        """Energy above hanging of a state ``(q, ω)`` (J)."""
        q, omega = state[self.attitude.quaternion], state[self.attitude.omega]
        return self.potential(q) - self.rest_energy + 0.5 * float(omega @ self.inertia(q) @ omega)

    def divergence(self, states: np.ndarray, controls: np.ndarray) -> float:
        """How far a trajectory's energy outgrew what its actuators can put in, in units of the energy span.

        Over a control period actuator ``i`` does at most ``T·|u_i|·max|d_i·ω|`` of work (``d_i``
        its direction, ω at either end of the period: within a well-resolved step the speed along
        ``d_i`` lies between them up to the integrator's error), and damping only takes energy
        away. A trajectory whose energy rises above the start's plus that cumulative bound was not
        moved by its controls but by the integrator: MuJoCo's semi-implicit steps diverge on a body
        whose inertia about one axis is tiny next to the others once it spins fast (ball scenes
        at 1:30 whose data reached 680 rad/s, and whose models trained on them never fitted:
        docs/scene-families.md).
        """
        states = np.asarray(states, dtype=float)
        energy = np.array([self.energy(state) for state in states])
        along = np.abs(states[:, self.attitude.omega] @ self.directions.T)
        work = self.scales.step_size * np.sum(np.abs(controls) * np.maximum(along[:-1], along[1:]), axis=1)
        bound = energy[0] + np.concatenate([[0.0], np.cumsum(work)])
        return float(np.max(energy - bound) / self.scales.energy_span)

    def within_band(self, state: np.ndarray, u: np.ndarray, stalled: np.ndarray | None = None) -> np.ndarray:
        """``u``, or braking (:meth:`pump` against the motion) once the state's energy is above
        ``MAX_ENERGY·ΔE``: all a swing-up passes through. Random levels and pumping kept on a strong
        motor tumble the body at many times the span (a two-motor ball scene at 13 spans at the 95th
        percentile, 44 % of its states past the speed the model's step resolves, validation loss 0.6
        where the family's other members reach 1e-3: docs/scene-families.md)."""
        if self.energy(state) <= MAX_ENERGY * self.scales.energy_span:
            return u
        return self.pump(state[self.attitude.omega], -1.0, stalled)

    def pump(self, omega: np.ndarray, sign: float = 1.0, stalled: np.ndarray | None = None) -> np.ndarray:
        """Every actuator at the bound that pushes along the motion (``sign = −1``: against it);
        where the body barely moves along an actuator's direction, ``stalled`` (±1 per actuator)
        picks the bound (``None``: the upper)."""
        along = self.directions @ np.asarray(omega, dtype=float) * sign
        slow = np.abs(along) < 1e-3 * self.scales.speed * np.linalg.norm(self.directions, axis=1)
        choice = np.where(along > 0.0, 1.0, -1.0)
        if stalled is not None:
            choice = np.where(slow, stalled, choice)
        return np.where(choice > 0.0, self.high, self.low)


def actuator_directions(env: Any) -> np.ndarray:
    """``(m, 3)``: row ``i`` is the body-frame direction along which a positive control of actuator
    ``i`` does positive work (power ``u_i·(d_i·ω)``), read off MuJoCo (the generalized force of a unit
    control, so gear and gain signs count)."""
    base = env.unwrapped
    model = base.model
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    axis = base.joint_axis
    directions = np.zeros((model.nu, 3))
    for i in range(model.nu):
        data.ctrl[:] = 0.0
        # A control inside the range (MuJoCo clamps); its sign only scales the direction.
        level = base.torque_high[i] if base.torque_high[i] != 0.0 else base.torque_low[i]
        data.ctrl[i] = level
        mujoco.mj_forward(model, data)
        force = np.asarray(data.qfrc_actuator, dtype=float) / level
        directions[i] = force[0] * axis if axis is not None else force[:3]
    return directions


def energy_spread_state(env: Any, physics: SwingPhysics, rng: np.random.Generator,
                        max_energy: float = MAX_ENERGY) -> tuple[np.ndarray, np.ndarray]:
    """A joint state whose energy above hanging is uniform in ``[0, max_energy·ΔE]`` at a random
    orientation (redrawn while the orientation alone is above the energy; after 20 tries at rest)."""
    target = rng.uniform(0.0, max_energy) * physics.scales.energy_span
    for _ in range(20):
        qpos, _ = random_joint_state(env, rng, 0.0)
        observation, _ = env.reset(options={"qpos": qpos})
        kinetic = target - (physics.potential(observation[physics.attitude.quaternion]) - physics.rest_energy)
        if kinetic >= 0.0:
            break
    else:
        return qpos, np.zeros(env.unwrapped.model.nv)
    axis = env.unwrapped.joint_axis
    if axis is not None:
        inertia = physics.inertia(observation[physics.attitude.quaternion])
        speed = math.sqrt(2.0 * kinetic / float(axis @ inertia @ axis))
        return qpos, np.array([speed if rng.uniform() < 0.5 else -speed])
    # On a ball joint the kinetic energy goes in a random direction, redrawn while it would spin the
    # body faster than START_SPEED_CAP·ω_s: all of it about an axis of small inertia (a long body's
    # own axis, down to 1:50) is a spin no swing-up passes through, at speeds the simulator's
    # integration does not resolve. After 20 draws the last direction at the cap (less energy).
    inertia = physics.inertia(observation[physics.attitude.quaternion])
    cap = START_SPEED_CAP * physics.scales.speed
    for _ in range(20):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        speed = math.sqrt(2.0 * kinetic / float(direction @ inertia @ direction))
        if speed <= cap:
            break
    return qpos, direction * min(speed, cap)


def switching_controls(env: Any, physics: SwingPhysics, rng: np.random.Generator, steps: int,
                       observation: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Roll the env ``steps`` periods from ``observation`` under the switching policy (module
    docstring); returns ``(states (steps+1, n), controls (steps, m), steps per segment kind)``."""
    kinds, weights = list(SEGMENTS), np.array(list(SEGMENTS.values()))
    states, controls = [observation], []
    counts = dict.fromkeys(kinds, 0)
    remaining, kind, level, stalled = 0, "coast", None, None
    for _ in range(steps):
        if remaining == 0:
            remaining = int(rng.integers(1, physics.scales.dwell_steps + 1))
            kind = kinds[int(rng.choice(len(kinds), p=weights / weights.sum()))]
            level = rng.uniform(physics.low, physics.high)
            stalled = rng.choice([-1.0, 1.0], size=physics.low.size)
        remaining -= 1
        counts[kind] += 1
        omega = states[-1][physics.attitude.omega]
        if kind == "pump":
            u = physics.pump(omega, 1.0, stalled)
        elif kind == "brake":
            u = physics.pump(omega, -1.0, stalled)
        elif kind == "level":
            u = level
        else:
            u = np.zeros_like(physics.low)
        u = physics.within_band(states[-1], u, stalled)
        observation, *_ = env.step(u)
        states.append(observation)
        controls.append(u)
    return np.array(states), np.array(controls), counts


def _excite(env: Any, physics: SwingPhysics, rng: np.random.Generator, kind: str,
            steps: int) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """One trajectory from a start of ``kind`` (:data:`SHARES`): its states, controls, steps per segment kind."""
    scales = physics.scales
    if kind == "energy":
        qpos, qvel = energy_spread_state(env, physics, rng)
    elif kind == "near_goal":
        qpos, qvel = near_goal_joint_state(env, rng, 0.6, 0.5 * scales.speed)
    else:
        qpos, qvel = random_joint_state(env, rng, 1.5 * scales.speed)
    observation, _ = env.reset(seed=int(rng.integers(2**31)), options={"qpos": qpos, "qvel": qvel})
    if kind != "uniform":
        return switching_controls(env, physics, rng, steps, observation)
    controls = control_sequence(rng, physics.low, physics.high, steps, "piecewise", scales.dwell_steps)
    states = [observation]
    for k in range(steps):
        controls[k] = physics.within_band(states[-1], controls[k])
        states.append(env.step(controls[k])[0])
    return np.array(states), controls, {}


def collect_swings(scene: str = "pendulum", trajectories: int | None = None, steps: int | None = None,
                   seed: int = 0, body: str | None = None, control_period: float | None = None,
                   progress: bool = True) -> Trajectories:
    """Seeded trajectories that excite what a swing-up needs (module docstring), sized from the
    scene's :class:`SwingScales` unless ``trajectories``/``steps`` are given.

    A trajectory on which the simulator diverged (:meth:`SwingPhysics.divergence` above
    :data:`DIVERGENCE_TOLERANCE`) is replaced by a fresh one from a new start of the same kind and
    counted (``diverged_trajectories``, with a warning); :data:`MAX_DIVERGED_IN_A_ROW` in a row
    raise: the scene's timestep does not resolve its motion.

    Metadata: the scales, the number of trajectories per kind of start, the share of saturated
    controls and the energy reached (``energy_coverage``: the highest and the 5th–95th percentile
    energies above hanging over all states, in units of the energy span).
    """
    from tqdm.auto import tqdm

    env = RigidBodyEnv(scene=scene, body=body, control_period=control_period)
    physics = SwingPhysics(env)
    scales = physics.scales
    steps = steps or scales.trajectory_steps
    trajectories = trajectories or max(10, math.ceil(TRANSITIONS / steps))
    rng = np.random.default_rng(seed)
    cut = np.cumsum([SHARES["energy"], SHARES["near_goal"]]) * trajectories
    states = np.empty((trajectories, steps + 1, env.unwrapped.space.state_dim))
    controls = np.empty((trajectories, steps, physics.low.size))
    starts = dict.fromkeys(SHARES, 0)
    segments = dict.fromkeys(SEGMENTS, 0)
    diverged = 0
    for i in tqdm(range(trajectories), desc=f"collect {env.scene_spec.name} (swings)", disable=not progress):
        kind = "energy" if i < cut[0] else "near_goal" if i < cut[1] else "uniform"
        starts[kind] += 1
        for _ in range(MAX_DIVERGED_IN_A_ROW):
            states[i], controls[i], counts = _excite(env, physics, rng, kind, steps)
            if physics.divergence(states[i], controls[i]) <= DIVERGENCE_TOLERANCE:
                break
            diverged += 1
        else:
            model = env.unwrapped.model
            raise RuntimeError(
                f"{scene}: MuJoCo's integration diverged on {MAX_DIVERGED_IN_A_ROW} trajectories in a row from "
                f"'{kind}' starts (the energy outgrew what the actuators can put in by more than "
                f"{DIVERGENCE_TOLERANCE} energy spans); its timestep {model.opt.timestep:g} s does not resolve "
                "the body's motion: a smaller <option timestep> or the implicit integrator would")
        for name, count in counts.items():
            segments[name] += count
    if diverged:
        warnings.warn(f"{scene}: replaced {diverged} of {trajectories} trajectories on which MuJoCo's integration "
                      "diverged (energy beyond the actuators' work)", stacklevel=2)
    energies = np.array([[physics.energy(s) for s in trajectory] for trajectory in states]) / scales.energy_span
    saturated = (controls <= physics.low + 1e-12) | (controls >= physics.high - 1e-12)
    metadata = {
        "scene": str(scene), "body": env.unwrapped.body_name, "control_period": float(env.unwrapped.dt),
        "seed": seed, "trajectories": trajectories, "steps": steps, "transitions": trajectories * steps,
        "collector": SWING_EXCITATION, "hinge_axis": hinge_axis_record(env),
        "scales": {"energy_span": scales.energy_span, "speed": scales.speed, "natural_period": scales.natural_period,
                   "dwell_steps": scales.dwell_steps},
        "starts": starts, "segment_steps": segments, "diverged_trajectories": diverged,
        "saturated_share": float(saturated.mean()),
        "energy_coverage": {"max": float(energies.max()), "p5": float(np.percentile(energies, 5)),
                            "p95": float(np.percentile(energies, 95))},
    }
    env.close()
    return Trajectories.from_parts(*env.unwrapped.space.layout.split(states), controls, metadata)

"""Hypothesis strategies and bookkeeping for the hard-case suite (``tests/hard_cases``).

Everything is float64. Budgets: :func:`budget` scales a test's ``max_examples`` by the
active profile (``HYPOTHESIS_PROFILE``: ``ci`` ×1, the default; ``thorough`` ×10;
``dev`` ×0.1), so expensive properties keep few examples and cheap ones many.

:func:`counted` wraps a property's body so that every example Hypothesis actually runs is
counted; ``tests/conftest.py`` sums the counts over xdist workers and prints
``hypothesis: N generated cases`` at the end of the session.
"""

from __future__ import annotations

import functools
import os
from typing import Any, Callable

import numpy as np
from helpers import hinge  # noqa: F401  (one definition, also reached as S.hinge)
from hypothesis import strategies as st

# --------------------------------------------------------------------------- bookkeeping
#: Examples run in this process (one xdist worker, or the whole session without xdist).
CASES = {"count": 0}

PROFILE_SCALE = {"ci": 1.0, "thorough": 10.0, "dev": 0.1}


def profile_name() -> str:
    return os.environ.get("HYPOTHESIS_PROFILE", "ci")


def budget(examples: int) -> int:
    """``max_examples`` for a property that gets ``examples`` in the ``ci`` profile."""
    return max(1, int(round(examples * PROFILE_SCALE.get(profile_name(), 1.0))))


def counted(test: Callable[..., Any]) -> Callable[..., Any]:
    """Count each call of a property body (put it *under* ``@given``)."""

    @functools.wraps(test)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        CASES["count"] += 1
        return test(*args, **kwargs)

    return wrapper


# --------------------------------------------------------------------------- numbers
@functools.lru_cache(maxsize=None)
def floats(low: float, high: float) -> st.SearchStrategy[float]:
    """Finite float64 in ``[low, high]``."""
    return st.floats(low, high, allow_nan=False, allow_infinity=False, width=64)


@functools.lru_cache(maxsize=None)
def log_uniform(low: float, high: float) -> st.SearchStrategy[float]:
    """Positive floats spread over decades ``[low, high]`` (drawn as ``10**x``)."""
    return floats(np.log10(low), np.log10(high)).map(lambda x: float(10.0**x))


@functools.lru_cache(maxsize=None)
def signed_log_uniform(low: float, high: float) -> st.SearchStrategy[float]:
    """``±10**x`` with ``10**x ∈ [low, high]``."""
    return st.tuples(st.sampled_from((-1.0, 1.0)), log_uniform(low, high)).map(lambda p: p[0] * p[1])


#: Seeds of NumPy generators for the bulk of a case's geometry (directions, centres of mass,
#: actuator axes). Hypothesis spends ~50 µs per drawn float; drawing one seed instead of a dozen
#: floats keeps ~1e4 cases affordable, while the parameters that make a case hard (spin, step
#: count, condition number, scales, special axes and zeros) are drawn by Hypothesis itself.
SEEDS = st.integers(0, 2**32 - 1)


@functools.lru_cache(maxsize=None)
def vectors(n: int, low: float, high: float) -> st.SearchStrategy[np.ndarray]:
    """``(n,)`` uniform in ``[low, high]`` (from a seed), or all zeros, or one end of the box."""
    seeded = SEEDS.map(lambda seed: np.random.default_rng(seed).uniform(low, high, size=n))
    corners = st.sampled_from([np.zeros(n), np.full(n, float(low)), np.full(n, float(high))]).map(np.array)
    return st.one_of(seeded, corners) if low <= 0.0 <= high else seeded


def _normalized(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


_DIRECTIONS = SEEDS.map(lambda seed: _normalized(np.random.default_rng(seed).normal(size=3)))
_AXES_3 = st.sampled_from([sign * axis for axis in np.eye(3) for sign in (1.0, -1.0)]).map(np.array)
_QUATERNIONS = SEEDS.map(lambda seed: _normalized(np.random.default_rng(seed).normal(size=4)))
_AXES_4 = st.sampled_from([sign * axis for axis in np.eye(4) for sign in (1.0, -1.0)]).map(np.array)


def unit_vectors() -> st.SearchStrategy[np.ndarray]:
    """A direction in R³: uniform on the sphere, or ± a coordinate axis."""
    return st.one_of(_AXES_3, _DIRECTIONS)


def unit_quaternions() -> st.SearchStrategy[np.ndarray]:
    """A unit quaternion (w, x, y, z), uniform on S³ (either sign), or ±1, ±i, ±j, ±k."""
    return st.one_of(_AXES_4, _QUATERNIONS)


def rotation_matrix(q: np.ndarray) -> np.ndarray:
    """``R(q)`` (body → world) for a unit quaternion, written independently of the package."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    return rotation_matrix(_normalized(rng.normal(size=4)))


def random_inertia(rng: np.random.Generator, scale: float, log_condition: float, physical: bool = True) -> np.ndarray:
    """``R diag(d) Rᵀ`` with a random rotation and condition number ``10^log_condition``.

    ``physical``: the principal moments ``a ≤ b ≤ c = scale`` obey the triangle inequality
    ``c ≤ a + b`` of every mass distribution (``a = c·10^−log_condition``, e.g. a thin rod
    ``(ε, 1, 1)``). Otherwise any SPD matrix (a learned ``J`` need not be physical):
    ``scale·[1, 10^(u·c), 10^c]``. Non-physical ``J`` make Euler's equations stiff (rates
    ``(J₂ − J₃)/J₁·ω²`` unbounded in the condition number)."""
    if physical:
        c = scale
        a = c * 10.0 ** (-log_condition)
        b = rng.uniform(max(a, c - a), c)
        d = np.array([a, b, c])
    else:
        d = scale * 10.0 ** (log_condition * np.array([0.0, rng.uniform(), 1.0]))
    rotation = random_rotation(rng)
    inertia = rotation @ np.diag(d) @ rotation.T
    return 0.5 * (inertia + inertia.T)


def as_tuple_matrix(matrix: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(x) for x in row) for row in np.atleast_2d(matrix))


def make_body(seed: int, scale: float, log_condition: float, gravity: bool, control_dim: int,
              damping: bool = False, physical: bool = True) -> Any:
    """A :class:`~fvin_mpc.core.rigid_body.PivotedRigidBody` from a seed and the drawn key parameters:
    inertia ``random_inertia(scale, log_condition)`` (isotropic when ``log_condition = 0``),
    centre of mass ``|c_i| ≤ 1`` m, ``m g ∈ [0.1, 20]`` N (or 0), actuator axes in ``[−2, 2]``,
    damping in ``[0, 0.5]`` N·m·s (or 0)."""
    from fvin_mpc.core.rigid_body import PivotedRigidBody

    rng = np.random.default_rng(seed)
    inertia = scale * np.eye(3) if log_condition == 0.0 else random_inertia(rng, scale, log_condition, physical)
    com = rng.uniform(-1.0, 1.0, size=3)
    mass_gravity = rng.uniform(0.1, 20.0) if gravity else 0.0
    axes = rng.uniform(-2.0, 2.0, size=(3, control_dim))
    d = rng.uniform(0.0, 0.5) if damping else 0.0
    return PivotedRigidBody(inertia=as_tuple_matrix(inertia), center_of_mass=tuple(float(c) for c in com),
                            mass_gravity=float(mass_gravity), actuator_axes=as_tuple_matrix(axes), damping=float(d))


@functools.lru_cache(maxsize=None)
def rigid_bodies(max_condition: float = 1e3, isotropic: bool = False, gravity: bool | None = None,
                 damping: bool = False, control_dim: int | None = None,
                 scales: tuple[float, float] = (1e-2, 10.0), physical: bool = True) -> st.SearchStrategy[Any]:
    """Random :func:`make_body` bodies; Hypothesis draws the scale, the condition number (log-uniform
    up to ``max_condition``, or 1), gravity on/off and ``m`` (1…3) unless fixed. ``physical``: see
    :func:`random_inertia`."""
    conditions = st.just(0.0) if isotropic else st.one_of(st.just(0.0), floats(0.0, float(np.log10(max_condition))),
                                                          st.just(float(np.log10(max_condition))))
    return st.builds(
        make_body, SEEDS, log_uniform(*scales), conditions,
        st.booleans() if gravity is None else st.just(gravity),
        st.integers(1, 3) if control_dim is None else st.just(control_dim),
        st.just(damping), st.just(physical),
    )


# --------------------------------------------------------------------------- components
def components(*arrays: np.ndarray) -> tuple[tuple[np.ndarray, ...], ...]:
    """``(4,)``/``(3,)`` vectors → tuples of ``(1,)`` NumPy components for :func:`fvin_mpc.core.fvin.fvin_step`."""
    return tuple(tuple(np.array([float(c)]) for c in np.atleast_1d(a)) for a in arrays)


def stacked(component_tuple: tuple[Any, ...]) -> np.ndarray:
    """Tuple of ``(1,)`` components (NumPy or torch) → flat float64 array."""
    return np.array([float(np.asarray(c.detach() if hasattr(c, "detach") else c).ravel()[0])
                     for c in component_tuple])




def non_finite_arrays(shape: tuple[int, ...], low: float = -5.0, high: float = 5.0) -> st.SearchStrategy[np.ndarray]:
    """Arrays of ``shape`` with at least one NaN/±inf entry."""

    @st.composite
    def build(draw: Any) -> np.ndarray:
        values = np.array(draw(st.lists(floats(low, high), min_size=int(np.prod(shape)),
                                        max_size=int(np.prod(shape)))), dtype=float).reshape(shape)
        flat = values.reshape(-1)
        positions = draw(st.lists(st.integers(0, flat.size - 1), min_size=1, max_size=flat.size, unique=True))
        for p in positions:
            flat[p] = draw(st.sampled_from((np.nan, np.inf, -np.inf)))
        return values

    return build()


def wrong_shapes(correct: tuple[int, ...]) -> st.SearchStrategy[tuple[int, ...]]:
    """Shapes (up to 2-D, sizes 0…8) other than ``correct``."""
    return st.lists(st.integers(0, 8), min_size=0, max_size=2).map(tuple).filter(lambda s: s != correct)


# --------------------------------------------------------------------------- independent rigid-body math
def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product, written independently of :mod:`fvin_mpc.s3`."""
    pw, pv, qw, qv = p[0], np.asarray(p[1:]), q[0], np.asarray(q[1:])
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def gravity_torque(body: Any, q: np.ndarray) -> np.ndarray:
    """Body-frame torque of gravity (−z in the world) about the pivot: ``c × Rᵀ(−m g e_z)``."""
    c = np.asarray(body.center_of_mass, dtype=float)
    return np.cross(c, rotation_matrix(q).T @ np.array([0.0, 0.0, -body.mass_gravity]))


def physical_torque(body: Any, q: np.ndarray, omega: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Gravity + actuators (``B u``) − damping (``d ω``), body frame (N·m)."""
    b = np.array(body.actuator_axes, dtype=float)
    return gravity_torque(body, q) + b @ np.atleast_1d(u) - body.damping * np.asarray(omega)


def implicit_rhs(body: Any, q: np.ndarray, omega: np.ndarray, u: np.ndarray, h: float) -> np.ndarray:
    """``C`` of DESIGN.md step 2 from physical quantities: ``π = 2Jω`` and the ξ-gradient of U is
    −2 × the gravity torque, the generalized force 2× the physical one, so
    ``C = −(h/2) J ω − (h²/4) τ``."""
    inertia = np.array(body.inertia, dtype=float)
    return -(h / 2.0) * inertia @ omega - (h * h / 4.0) * physical_torque(body, q, omega, u)


def omega_for_rhs_norm(body: Any, q: np.ndarray, direction: np.ndarray, u: np.ndarray, h: float,
                       target: float) -> float | None:
    """``λ ≥ 0`` with ``|C(q, λ·direction, u)| = target`` (no damping: C is affine in ω), or ``None``."""
    inertia = np.array(body.inertia, dtype=float)
    a = -(h / 2.0) * inertia @ direction
    c0 = implicit_rhs(body, q, np.zeros(3), u, h)
    aa, ab, cc = a @ a, a @ c0, c0 @ c0 - target * target
    disc = ab * ab - aa * cc
    if disc < 0:
        return None
    root = (-ab + np.sqrt(disc)) / aa
    return float(root) if root >= 0 else None

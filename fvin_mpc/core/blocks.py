"""A state as a product of blocks, one per joint of a kinematic tree (or per part of a free body).

jaxlie's shape: every block kind writes its chart (``retract``/``local``), its check, its distance to a
goal and its sizes once, on components (:mod:`fvin_mpc.core.backend`), so the same code runs on NumPy,
torch and CasADi; a :class:`StateLayout` composes them for whole states.

A state is MuJoCo's ``(qpos, qvel)`` of the blocks in the tree's order: every block's *position* entries
first, then every block's *rate* entries. Each block's position and rate are its joint's ``qpos`` and
``qvel`` (``../shared/DESIGN.md``, "Mechanisms"):

============  ===============================  ==========================  ========  =========
block         position (``qpos``)              rate (``qvel``)             chart     rates
============  ===============================  ==========================  ========  =========
:class:`Slide`     ``s`` (``size`` entries)       ``ṡ``                       addition  linear
:class:`Hinge`     ``θ`` (rad, wrap-free)          ``θ̇``                       ``Δθ`` on the circle  angular
:class:`Ball`      ``q = (w, x, y, z)``, sign-free   ``ω`` in the child's frame  Gibbs vector  angular
:class:`FreeJoint` ``(p, q)``, ``p`` in the world  ``(v, ω)``: world, body   both      both
============  ===============================  ==========================  ========  =========

So a pivoted body's ``(q, ω)`` is ``StateLayout((Ball(),))`` and a free body's ``(x, q, v, ω)`` is
``StateLayout((FreeJoint(),))``: today's single-body states, entry for entry. Local coordinates
``δ`` follow the same order: every block's chart coordinates, then every rate (rates add).

Adding a block kind is a subclass here with its sizes, ``retract``, ``local``, ``normalized`` and
``distance``; every consumer reads a state through the layout's slices (:class:`BlockSlots`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Sequence

import numpy as np

from fvin_mpc.core import s3
from fvin_mpc.core.backend import Ops, get_ops
from fvin_mpc.core.state import UNIT_NORM_TOLERANCE, as_float_array

NP = get_ops("numpy")
Components = Sequence[Any]


# ----------------------------------------------------------------------------- S³ chart on components
def chart_retract(q_bar: s3.Quat, theta: s3.Vec3, ops: Ops) -> s3.Quat:
    """``q̄ ⊗ (1, θ)/√(1 + |θ|²)`` on components (any backend): the Gibbs-vector chart of S³ at ``q̄``."""
    return s3.scale(1.0 / ops.sqrt(1.0 + s3.dot(theta, theta)), s3.multiply(q_bar, (1.0, *theta)))


def chart_local(q_bar: s3.Quat, q: s3.Quat) -> s3.Vec3:
    """``Im(p)/Re(p)`` with ``p = q̄* ⊗ q`` — the inverse of :func:`chart_retract`, the same for ``±q``."""
    p = s3.multiply(s3.conjugate(q_bar), q)
    return tuple(component / p[0] for component in p[1:])


# ----------------------------------------------------------------------------- block kinds
@dataclass(frozen=True)
class Block:
    """One joint's part of a state. Subclasses fix the sizes and write the chart once, on components.

    Attributes:
        label: the joint's name, for messages (``""``: unnamed).
    """

    label: str = ""

    #: the kind's name in messages and in the C controller's block table
    kind: ClassVar[str] = "block"
    #: entries of the block's position in a state (its joint's ``qpos``)
    position_size: ClassVar[int]
    #: chart coordinates of the position, which is also the number of rate entries (its joint's ``qvel``)
    tangent_size: ClassVar[int]
    #: per chart coordinate: ``"position"`` (a length) or ``"angle"`` (rad), for trust regions and bounds
    chart_units: ClassVar[tuple[str, ...]]
    #: per rate entry: whether it is an angular rate, bounded by the step's solvability limit ``h|ω| < 1``
    angular_rates: ClassVar[tuple[bool, ...]]
    #: per chart coordinate: the factor that makes it, to first order, the displacement or rotation angle it
    #: stands for (a Gibbs vector is ``tan(α/2)`` about its axis: 2)
    chart_scales: ClassVar[tuple[float, ...]]
    #: where within the position a unit quaternion sits, if the block has one
    quaternion_offset: ClassVar[int | None] = None

    def retract(self, base: Components, delta: Components, ops: Ops) -> tuple[Any, ...]:
        """The position at chart coordinates ``delta`` around ``base``."""
        raise NotImplementedError

    def local(self, base: Components, point: Components, ops: Ops) -> tuple[Any, ...]:
        """The inverse of :meth:`retract`: ``point``'s chart coordinates around ``base``."""
        raise NotImplementedError

    def normalized(self, position: np.ndarray, name: str) -> np.ndarray:
        """A measured position (NumPy, ``(position_size,)``) made exact, or ``ValueError``."""
        return position

    def distance(self, position: Components, goal: Components, ops: Ops) -> Any:
        """How far ``position`` is from ``goal``: zero on it, invariant where the block's representation is
        not unique (a quaternion's sign, an angle's turns)."""
        raise NotImplementedError


@dataclass(frozen=True)
class Slide(Block):
    """A prismatic joint, or any Euclidean part of a state (a free body's world position): ``size``
    entries, their rates, the chart by addition."""

    size: int = 1

    kind: ClassVar[str] = "slide"

    def __post_init__(self) -> None:
        if self.size < 1:
            raise ValueError(f"a slide block needs size >= 1, got {self.size}")

    # Sizes depend on the instance here; the ClassVar annotations above describe the protocol.
    @property  # type: ignore[override]
    def position_size(self) -> int:
        return self.size

    @property  # type: ignore[override]
    def tangent_size(self) -> int:
        return self.size

    @property  # type: ignore[override]
    def chart_units(self) -> tuple[str, ...]:
        return ("position",) * self.size

    @property  # type: ignore[override]
    def angular_rates(self) -> tuple[bool, ...]:
        return (False,) * self.size

    @property  # type: ignore[override]
    def chart_scales(self) -> tuple[float, ...]:
        return (1.0,) * self.size

    def retract(self, base, delta, ops):
        return tuple(b + d for b, d in zip(base, delta))

    def local(self, base, point, ops):
        return tuple(p - b for b, p in zip(base, point))

    def distance(self, position, goal, ops):
        return sum((p - g) * (p - g) for p, g in zip(position, goal))


@dataclass(frozen=True)
class Hinge(Block):
    """A revolute joint as its angle ``θ`` (rad) and rate ``θ̇``: wrap-free — ``local`` is the difference on
    the circle (in ``(−π, π]``) and ``distance`` is ``sin²(Δθ/2)``, the quaternion's ``1 − ⟨q, q_goal⟩²`` of
    the same rotation."""

    kind: ClassVar[str] = "hinge"
    position_size: ClassVar[int] = 1
    tangent_size: ClassVar[int] = 1
    chart_units: ClassVar[tuple[str, ...]] = ("angle",)
    angular_rates: ClassVar[tuple[bool, ...]] = (True,)
    chart_scales: ClassVar[tuple[float, ...]] = (1.0,)

    def retract(self, base, delta, ops):
        return (base[0] + delta[0],)

    def local(self, base, point, ops):
        difference = point[0] - base[0]
        return (ops.atan2(ops.sin(difference), ops.cos(difference)),)

    def distance(self, position, goal, ops):
        half = ops.sin(0.5 * (position[0] - goal[0]))
        return half * half


@dataclass(frozen=True)
class Ball(Block):
    """A body's attitude on S³ — a ball joint, or a pivoted body on a hinge kept on S³ (the S3FVIN's
    state): ``q = (w, x, y, z)`` and the body-frame ``ω``. The chart is the Gibbs vector
    (:func:`chart_retract`), the same for ``±q``; ``distance`` is ``1 − ⟨q, q_goal⟩²``."""

    kind: ClassVar[str] = "ball"
    position_size: ClassVar[int] = 4
    tangent_size: ClassVar[int] = 3
    chart_units: ClassVar[tuple[str, ...]] = ("angle",) * 3
    angular_rates: ClassVar[tuple[bool, ...]] = (True,) * 3
    chart_scales: ClassVar[tuple[float, ...]] = (2.0,) * 3
    quaternion_offset: ClassVar[int | None] = 0

    def retract(self, base, delta, ops):
        return chart_retract(tuple(base), tuple(delta), ops)

    def local(self, base, point, ops):
        return chart_local(tuple(base), tuple(point))

    def normalized(self, position, name):
        """Policy: within ``UNIT_NORM_TOLERANCE`` of unit norm a quaternion is normalized (float32
        observations, sensor rounding); further is refused — normalizing a wrong one hides a bug upstream."""
        norm = float(np.linalg.norm(position))
        if abs(norm - 1.0) > UNIT_NORM_TOLERANCE:
            where = f" of {name}" if name else ""
            raise ValueError(f"q{where} is not a unit quaternion (|q| = {norm:.6g}; tolerance {UNIT_NORM_TOLERANCE})")
        return position / norm

    def distance(self, position, goal, ops):
        cosine = s3.dot(tuple(position), tuple(goal))
        return 1.0 - cosine * cosine


@dataclass(frozen=True)
class FreeJoint(Block):
    """A free body: world position ``p`` and attitude ``q`` (MuJoCo's free-joint ``qpos``), world velocity
    ``v`` and body rate ``ω`` (its ``qvel``) — a :class:`Slide` of three and a :class:`Ball` side by side."""

    kind: ClassVar[str] = "free"
    position_size: ClassVar[int] = 7
    tangent_size: ClassVar[int] = 6
    chart_units: ClassVar[tuple[str, ...]] = ("position",) * 3 + ("angle",) * 3
    angular_rates: ClassVar[tuple[bool, ...]] = (False,) * 3 + (True,) * 3
    chart_scales: ClassVar[tuple[float, ...]] = (1.0,) * 3 + (2.0,) * 3
    quaternion_offset: ClassVar[int | None] = 3

    _TRANSLATION: ClassVar[Slide] = Slide(size=3)
    _ATTITUDE: ClassVar[Ball] = Ball()

    def retract(self, base, delta, ops):
        return (*self._TRANSLATION.retract(base[:3], delta[:3], ops), *self._ATTITUDE.retract(base[3:], delta[3:], ops))

    def local(self, base, point, ops):
        return (*self._TRANSLATION.local(base[:3], point[:3], ops), *self._ATTITUDE.local(base[3:], point[3:], ops))

    def normalized(self, position, name):
        return np.concatenate([position[:3], self._ATTITUDE.normalized(position[3:], name)])

    def distance(self, position, goal, ops):
        return self._TRANSLATION.distance(position[:3], goal[:3], ops) + \
            self._ATTITUDE.distance(position[3:], goal[3:], ops)


# ----------------------------------------------------------------------------- the product
@dataclass(frozen=True)
class BlockSlots:
    """Where one block's entries sit: ``position`` and ``rate`` in a state, ``chart`` and ``tangent_rate`` in
    local coordinates ``δ``; ``quaternion`` in a state where the block has one (else ``None``)."""

    block: Block
    position: slice
    rate: slice
    chart: slice
    tangent_rate: slice
    quaternion: slice | None


@dataclass(frozen=True)
class Attitude:
    """One body's attitude in a state: its quaternion and body rate ``ω`` (in a state), their chart
    coordinates and rate (in ``δ``) — what single-body code reads (:meth:`StateLayout.attitude`)."""

    quaternion: slice
    omega: slice
    chart: slice
    tangent_omega: slice


def _slice_of(indices: Sequence[int]) -> slice | list[int]:
    """Contiguous indices as a slice (a view, as NumPy slices a state), others as a list (NumPy and CasADi
    both index by one)."""
    if len(indices) and list(indices) == list(range(indices[0], indices[0] + len(indices))):
        return slice(indices[0], indices[0] + len(indices))
    return list(indices)


@dataclass(frozen=True)
class FreeBody:
    """A free body's parts in a state (:meth:`StateLayout.free_body`): world position, attitude, world
    velocity, body rate."""

    position: slice
    quaternion: slice
    velocity: slice
    omega: slice


def _attitude_of(slots: Sequence[BlockSlots]) -> Attitude | None:
    """The attitude of the one block with a quaternion, ``None`` where there are none or several."""
    found = [slot for slot in slots if slot.quaternion is not None]
    if len(found) != 1:
        return None
    slot = found[0]
    offset = slot.quaternion.start - slot.position.start  # the chart's and the rate's offset alike
    return Attitude(slot.quaternion, slice(slot.rate.start + offset, slot.rate.start + offset + 3),
                    slice(slot.chart.start + offset, slot.chart.start + offset + 3),
                    slice(slot.tangent_rate.start + offset, slot.tangent_rate.start + offset + 3))


def _free_body_of(slots: Sequence[BlockSlots]) -> FreeBody | None:
    """The parts of the one :class:`FreeJoint` block, ``None`` where there are none or several."""
    found = [slot for slot in slots if isinstance(slot.block, FreeJoint)]
    if len(found) != 1:
        return None
    p, r = found[0].position.start, found[0].rate.start
    return FreeBody(slice(p, p + 3), slice(p + 3, p + 7), slice(r, r + 3), slice(r + 3, r + 6))


def single_attitude(layout: "StateLayout") -> Attitude | None:
    """``layout``'s one attitude (:meth:`StateLayout.attitude`), ``None`` where it has none or several."""
    return layout._attitude


@dataclass(frozen=True)
class StateLayout:
    """A state as the product of ``blocks`` (module docstring): all positions, then all rates.

    Attributes:
        blocks: the blocks in the tree's order.
        name: a label for messages, e.g. ``"(q, ω)"``.
    """

    blocks: tuple[Block, ...]
    name: str

    # Index facts, computed once (a measured state is sliced by them on every controller call).
    state_dim: int = field(init=False)
    #: entries of ``δ``: every block's chart coordinates and every rate
    tangent_dim: int = field(init=False)
    #: every block's entries, in block order
    slots: tuple[BlockSlots, ...] = field(init=False)
    #: every position entry of a state (MuJoCo's ``qpos``)
    positions: slice = field(init=False)
    #: every rate entry of a state (MuJoCo's ``qvel``): what a control changes within one step
    rates: slice = field(init=False)
    #: every rate's entry in ``δ``
    tangent_rates: slice = field(init=False)
    #: the state's entries that are angular rates (bounded by the step's solvability limit)
    angular_rates: slice | list[int] = field(init=False)
    #: per entry of ``δ``: ``"position"``, ``"angle"``, ``"velocity"`` or ``"angular rate"``
    tangent_units: tuple[str, ...] = field(init=False)
    #: ``(quaternion entries, other entries, join order)``: index lists (NumPy and torch index by them) for
    #: :meth:`split` and its inverse, ``concatenate([q, rest])[..., join order]``
    split_entries: tuple[list[int], list[int], list[int]] = field(init=False, repr=False)
    # The one attitude and the one free body where the state has exactly one (read on every controller call).
    _attitude: Attitude | None = field(init=False, repr=False)
    _free_body: FreeBody | None = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.blocks or not all(isinstance(block, Block) for block in self.blocks):
            raise ValueError(f"a state layout needs one or more blocks, got {self.blocks!r}")
        n_position = sum(block.position_size for block in self.blocks)
        n_chart = sum(block.tangent_size for block in self.blocks)
        slots, position, rate, chart = [], 0, n_position, 0
        for block in self.blocks:
            offset = block.quaternion_offset
            slots.append(BlockSlots(
                block, slice(position, position + block.position_size), slice(rate, rate + block.tangent_size),
                slice(chart, chart + block.tangent_size),
                slice(n_chart + rate - n_position, n_chart + rate - n_position + block.tangent_size),
                None if offset is None else slice(position + offset, position + offset + 4)))
            position, rate = position + block.position_size, rate + block.tangent_size
            chart += block.tangent_size
        angular = [n_position + i for i, flag in enumerate(f for b in self.blocks for f in b.angular_rates) if flag]
        units = [*(u for b in self.blocks for u in b.chart_units),
                 *("angular rate" if f else "velocity" for b in self.blocks for f in b.angular_rates)]
        quaternion = [i for slot in slots if slot.quaternion is not None
                      for i in range(slot.quaternion.start, slot.quaternion.stop)]
        other = [i for i in range(rate) if i not in set(quaternion)]
        facts = {"state_dim": rate, "tangent_dim": 2 * n_chart, "slots": tuple(slots),
                 "split_entries": (quaternion, other, np.argsort(quaternion + other).tolist()),
                 "positions": slice(0, n_position), "rates": slice(n_position, rate),
                 "tangent_rates": slice(n_chart, 2 * n_chart), "angular_rates": _slice_of(angular),
                 "tangent_units": tuple(units)}
        facts.update(_attitude=_attitude_of(slots), _free_body=_free_body_of(slots))
        for name, value in facts.items():
            object.__setattr__(self, name, value)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, StateLayout) and self.blocks == other.blocks

    def __hash__(self) -> int:
        return hash(self.blocks)

    # -------------------------------------------------------------- reading a state
    @property
    def quaternions(self) -> tuple[slice, ...]:
        """Every unit quaternion's entries in a state, in block order."""
        return tuple(slot.quaternion for slot in self.slots if slot.quaternion is not None)

    def attitude(self, by: str) -> Attitude:
        """The one body attitude of a single-body state (a :class:`Ball` or :class:`FreeJoint` block):
        what code written for one rotating body reads. ``ValueError`` naming ``by`` (the code that asked)
        for a layout with no attitude or several."""
        if self._attitude is None:
            raise ValueError(f"{by} is written for one body's attitude; the state {self.name} has "
                             f"{len(self.quaternions)} ({', '.join(slot.block.kind for slot in self.slots)})")
        return self._attitude

    def free_body(self, by: str) -> FreeBody:
        """The one :class:`FreeJoint` block's parts: what code written for a free-flying craft reads.
        ``ValueError`` naming ``by`` for a layout with no free joint or several."""
        if self._free_body is None:
            free = sum(isinstance(block, FreeJoint) for block in self.blocks)
            raise ValueError(f"{by} is written for one free body; the state {self.name} has {free} free joints")
        return self._free_body

    def check(self, x: Any) -> np.ndarray:
        """A measured state as a float64 copy, each block's position made exact (a quaternion within
        ``UNIT_NORM_TOLERANCE`` of unit norm normalized, :meth:`Ball.normalized`).

        Raises:
            ValueError: wrong shape, NaN/inf, or a block's position refused.
        """
        x = as_float_array(x, (self.state_dim,), f"state {self.name}")
        for slot in self.slots:
            x[slot.position] = slot.block.normalized(x[slot.position], slot.block.label)
        return x


    def split(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States ``(…, n)`` as ``(quaternions (…, 4k), rest (…, n − 4k))``: every quaternion's entries in
        block order, and every other entry in state order (the data files' ``q`` and ``rest``)."""
        quaternion, other, _ = self.split_entries
        return x[..., quaternion], x[..., other]

    def join(self, q: np.ndarray, rest: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`split`."""
        return np.concatenate([q, rest], axis=-1)[..., self.split_entries[2]]

    # -------------------------------------------------------------- the chart, on any backend
    def retract(self, x_bar: Any, delta: Any, ops: Ops = NP) -> Any:
        """A state from a base point ``x̄ (…, n)`` and local coordinates ``δ (…, tangent_dim)`` (NumPy and
        torch: stacked on the last axis; CasADi: columns): each block's position by its chart, rates by
        addition."""
        base, step = ops.unstack(x_bar), ops.unstack(delta)
        positions, rates = [], []
        for slot in self.slots:
            positions += slot.block.retract(base[slot.position], step[slot.chart], ops)
            rates += [b + d for b, d in zip(base[slot.rate], step[slot.tangent_rate])]
        return ops.stack([*positions, *rates])

    def local(self, x_bar: Any, x: Any, ops: Ops = NP) -> Any:
        """The inverse of :meth:`retract`: ``δ`` of ``x`` in ``x̄``'s chart (the same for ``±q``)."""
        base, point = ops.unstack(x_bar), ops.unstack(x)
        charts, rates = [], []
        for slot in self.slots:
            charts += slot.block.local(base[slot.position], point[slot.position], ops)
            rates += [p - b for b, p in zip(base[slot.rate], point[slot.rate])]
        return ops.stack([*charts, *rates])

    def distance(self, x: Any, goal: Any, ops: Ops = NP) -> Any:
        """The configuration's distance to a goal state: the sum of the blocks' :meth:`Block.distance`
        (rates do not count). NumPy/torch: ``(…,)``; CasADi: a scalar."""
        point, target = ops.unstack(x), ops.unstack(goal)
        return sum(slot.block.distance(point[slot.position], target[slot.position], ops) for slot in self.slots)

    def rates_over_step(self, delta: Any, step_size: float, ops: Ops = NP) -> Any:
        """Local coordinates ``δ`` between two states a step of ``step_size`` apart as rates: each chart
        coordinate times its block's :attr:`~Block.chart_scales` over the step (m/s, rad/s), the rates as
        they are — a residual whose entries are all in rate units."""
        components, n_chart = ops.unstack(delta), self.tangent_rates.start
        scales = [scale for block in self.blocks for scale in block.chart_scales]
        return ops.stack([*(scales[i] * components[i] / step_size for i in range(n_chart)), *components[n_chart:]])

    def tangent_limits(self, position: float, angle: float, velocity: float, angular_rate: float) -> np.ndarray:
        """One number per entry of ``δ`` by its unit (:attr:`tangent_units`): a trust region or a scale."""
        by_unit = {"position": position, "angle": angle, "velocity": velocity, "angular rate": angular_rate}
        return np.array([by_unit[unit] for unit in self.tangent_units], dtype=float)

    # -------------------------------------------------------------- MuJoCo's joint coordinates
    def qpos(self, x: np.ndarray) -> np.ndarray:
        """MuJoCo's ``qpos`` of the blocks' joints (every block's position is its joint's ``qpos``)."""
        return np.asarray(x, dtype=float)[..., self.positions]

    def qvel(self, x: np.ndarray) -> np.ndarray:
        """MuJoCo's ``qvel`` of the blocks' joints (every block's rate is its joint's ``qvel``)."""
        return np.asarray(x, dtype=float)[..., self.rates]

    def from_joints(self, qpos: Any, qvel: Any) -> np.ndarray:
        """The state of the joints' ``qpos``, ``qvel`` (:meth:`check`ed)."""
        return self.check(np.concatenate([np.ravel(qpos), np.ravel(qvel)]))

    def __repr__(self) -> str:
        return f"StateLayout({self.name!r}: {' × '.join(block.kind for block in self.blocks)})"

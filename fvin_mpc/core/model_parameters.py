"""Model parameters as run-time inputs: a small named vector ``p`` a controller can change without a new
export (online adaptation; a payload, a weaker motor).

A model's :class:`ModelParameters` lists its blocks, each a value the model's terms read as a constant
otherwise; an exported function that takes ``p`` builds the **same** terms code on symbols in their place
(a closed form's fields: :func:`parametrized_body`; a learned model's weights:
``fvin_mpc.control.model_export.parametrized_weights``), so the math keeps one source:

* ``gain_scale`` (``m``, default ones), every model: control ``j``'s effect is multiplied by ``s_j`` — the
  step sees ``s ⊙ u`` (:meth:`ModelParameters.actuated`; ``g(q) diag(s)`` and, for a free body, the force
  ``F_x(x, q, s ⊙ u)``). A weaker or stronger actuator, the disturbance estimate's multiplicative twin.
* a learned model: the weights named in :data:`LEARNED_PARAMETER_WEIGHTS` that it has (the constant damping
  ``D = L_D L_Dᵀ``, a constant inertia's or mass's Cholesky factor, the uniform field of a free body's
  potential) and the output layer of the potential network ``potential_w{L}`` (the scale of each hidden
  feature's energy: linear in ``U``).
* a learned model exported with ``low_rank=r`` (opt-in): a rank-``r`` correction of each other network's
  output layer (:func:`low_rank_blocks`) — ``W → W + C Σ_r V_rᵀ`` with ``W = U Σ Vᵀ`` the layer's own
  singular value decomposition and the block ``C`` (``out × r``, default zeros) the run-time input: linear in
  ``C``, and ``C = α U_r`` scales the layer's ``r`` strongest directions by ``1 + α``. What a black-box
  adaptation of a network fits (a low-rank subset of the networks' last layers, docs/adaptation.md), beside
  the physical blocks.
* a closed-form body: the fields its class names in ``PARAMETERS`` (pivoted body: ``inertia``,
  ``center_of_mass``, ``mass_gravity``, ``damping``; quadrotor: ``mass``, ``inertia``, ``gravity``). A
  scalar that is zero (no damping) stays a constant: it switches a term off, and a symbol would put the
  term back.

Flat names are ``block`` for a scalar, ``block[i]`` for a vector and ``block[i,j]`` for a matrix (row-major,
the order of the flat vector). Matrices are taken whole: set ``inertia[0,1]`` and ``inertia[1,0]`` together.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from itertools import product
from typing import Any, Mapping

import numpy as np

#: The per-actuator gain scale, the first block of every model's parameters.
GAIN_SCALE = "gain_scale"
#: The weights of a learned model that are parameters when it has them (explicit physical quantities).
LEARNED_PARAMETER_WEIGHTS = ("dissipation_cholesky", "inertia_cholesky", "mass_cholesky", "potential_linear")
#: The name of a low-rank correction's block is this prefix and its layer's weight name (``lowrank_gain_w2``).
LOW_RANK_PREFIX = "lowrank_"


@dataclass(frozen=True)
class ParameterBlock:
    """One named value: ``default`` has the shape the model's terms read (``()``, ``(n,)`` or ``(r, c)``)."""

    name: str
    default: np.ndarray

    @property
    def size(self) -> int:
        return int(self.default.size)

    @property
    def flat_names(self) -> tuple[str, ...]:
        shape = self.default.shape
        if not shape:
            return (self.name,)
        return tuple(f"{self.name}[{','.join(map(str, index))}]" for index in product(*map(range, shape)))


@dataclass(frozen=True)
class ModelParameters:
    """The parameter vector of one model: its blocks in order (module docstring)."""

    blocks: tuple[ParameterBlock, ...]

    @property
    def names(self) -> tuple[str, ...]:
        """Every entry's flat name, in the vector's order."""
        return tuple(name for block in self.blocks for name in block.flat_names)

    @property
    def defaults(self) -> np.ndarray:
        """The exported model's own values (with them a parametrized function equals the constant one)."""
        return np.concatenate([np.ravel(block.default) for block in self.blocks]).astype(float)

    @property
    def size(self) -> int:
        return sum(block.size for block in self.blocks)

    def slice(self, name: str) -> slice:
        """Where block ``name`` sits in the vector; ``KeyError`` naming the blocks if it has none."""
        start = 0
        for block in self.blocks:
            if block.name == name:
                return slice(start, start + block.size)
            start += block.size
        raise KeyError(f"no parameter block {name!r}; this model has {[block.name for block in self.blocks]}")

    def values(self, base: Any = None, **blocks: Any) -> np.ndarray:
        """A full vector: ``base`` (default: :attr:`defaults`) with the named ``blocks`` replaced, e.g.
        ``values(gain_scale=[0.8])``. ``ValueError`` on a wrong size or a non-finite entry."""
        vector = self.defaults if base is None else self.check(base)
        for name, value in blocks.items():
            where = self.slice(name)
            value = np.ravel(np.asarray(value, dtype=float))
            if value.size != where.stop - where.start:
                raise ValueError(f"parameter block {name!r} has {where.stop - where.start} entries, got {value.size}")
            vector[where] = value
        return self.check(vector)

    def check(self, vector: Any) -> np.ndarray:
        """``vector`` as a float array of this size, finite; ``ValueError`` otherwise."""
        vector = np.array(vector, dtype=float).ravel()
        if vector.size != self.size or not np.all(np.isfinite(vector)):
            raise ValueError(f"model parameters: need {self.size} finite values ({', '.join(self.names)}), "
                             f"got {vector.size}{'' if np.all(np.isfinite(vector)) else ' with non-finite entries'}")
        return vector

    def block(self, p: Any, name: str) -> list[Any]:
        """Block ``name``'s entries of ``p`` (NumPy vector or CasADi column), flat."""
        where = self.slice(name)
        return [p[i] for i in range(where.start, where.stop)]

    def shaped(self, p: Any, name: str) -> Any:
        """Block ``name`` of ``p`` (a CasADi column) in its default's nesting: a scalar, a tuple, a tuple of
        row tuples — the shape a closed-form body's fields have."""
        entries = self.block(p, name)
        shape = next(block.default.shape for block in self.blocks if block.name == name)
        if not shape:
            return entries[0]
        if len(shape) == 1:
            return tuple(entries)
        return tuple(tuple(entries[i * shape[1] + j] for j in range(shape[1])) for i in range(shape[0]))

    def actuated(self, u: Any, p: Any) -> Any:
        """The controls the model's step sees: ``s ⊙ u`` (``s`` the ``gain_scale`` block; CasADi columns)."""
        where = self.slice(GAIN_SCALE)
        return u * p[where.start:where.stop]

    def mass_ratio(self, p: Any) -> Any:
        """The free body's mass in ``p`` relative to the model's own: a closed form's ``mass`` over its default,
        a learned model's ``‖L_M‖²`` over its default's (``tr M`` less the constant ``ε_M``: exact for the
        uniform scale an estimated mass applies); ``1`` for a model with neither (a pivoted body, whose mass
        reaches its parameters as a gain scale)."""
        for name, power in (("mass", 1), ("mass_cholesky", 2)):
            if any(block.name == name for block in self.blocks):
                default = np.ravel(next(block.default for block in self.blocks if block.name == name))
                entries = self.block(p, name)
                own = float(np.sum(np.abs(default) ** power))
                return sum(entry ** power for entry in entries) / own
        return 1.0

    def control_effect(self, p: Any) -> Any:
        """Each control's effect relative to the exported model's: ``s / mass ratio`` (CasADi column or NumPy
        vector) — the acceleration a unit of control ``j`` gives, against what it gave before. A body ``b``
        times as heavy has effect ``1/b``; a rotor at 70 % has ``0.7``."""
        where = self.slice(GAIN_SCALE)
        return p[where.start:where.stop] / self.mass_ratio(p)


def gain_scale_block(control_dim: int) -> ParameterBlock:
    return ParameterBlock(GAIN_SCALE, np.ones(control_dim))


def learned_parameters(weights: Mapping[str, Any], config: Any, low_rank: int = 0) -> ModelParameters:
    """The parameters of a learned model (module docstring): the gain scale, the weights of
    :data:`LEARNED_PARAMETER_WEIGHTS` it has, the potential network's output layer, and with ``low_rank`` ``r``
    the rank-``r`` corrections of the other networks' output layers (:func:`low_rank_blocks`)."""
    names = [name for name in LEARNED_PARAMETER_WEIGHTS if name in weights]
    output = f"potential_w{config.hidden_layers}"
    if output in weights:
        names.append(output)
    return ModelParameters((gain_scale_block(config.control_dim),
                            *(ParameterBlock(name, np.array(weights[name], dtype=float)) for name in names),
                            *low_rank_blocks(weights, config.hidden_layers, low_rank)))


def low_rank_blocks(weights: Mapping[str, Any], hidden_layers: int, rank: int) -> tuple[ParameterBlock, ...]:
    """Zero blocks ``lowrank_{net}_w{L}`` (``out × min(rank, out, width)``) for every network's output layer
    ``{net}_w{L}`` but the potential's (a parameter whole already); ``()`` for ``rank`` 0."""
    if rank < 0:
        raise ValueError(f"a low-rank correction's rank is >= 0, got {rank}")
    if rank == 0:
        return ()
    layers = sorted(name for name in weights
                    if name.endswith(f"_w{hidden_layers}") and not name.startswith("potential_"))
    if not layers:
        raise ValueError("low_rank: this model has no network output layer to correct")
    shapes = {name: np.shape(weights[name]) for name in layers}
    return tuple(ParameterBlock(LOW_RANK_PREFIX + name, np.zeros((shapes[name][0], min(rank, *shapes[name]))))
                 for name in layers)


def low_rank_basis(layer: Any, rank: int) -> np.ndarray:
    """``Σ_r V_rᵀ`` (``rank × width``) of the output layer ``layer = U Σ Vᵀ``: its ``rank`` strongest input
    directions, each times its singular value — the right factor of :func:`low_rank_blocks`' corrections."""
    _, singular, right = np.linalg.svd(np.asarray(layer, dtype=float), full_matrices=False)
    return singular[:rank, None] * right[:rank]


def body_parameters(body: Any) -> ModelParameters:
    """The parameters of a closed-form body: the gain scale and the fields its class lists in
    ``PARAMETERS`` (a zero scalar left out: it switches a term off)."""
    blocks = [gain_scale_block(body.control_dim)]
    for name in getattr(type(body), "PARAMETERS", ()):
        value = np.array(getattr(body, name), dtype=float)
        if value.ndim == 0 and value == 0.0:
            continue
        blocks.append(ParameterBlock(name, value))
    return ModelParameters(tuple(blocks))


def parametrized_body(body: Any, parameters: ModelParameters, p: Any) -> Any:
    """``body`` (a frozen dataclass) with its parameter fields replaced by entries of the CasADi column ``p``."""
    fields = {block.name: parameters.shaped(p, block.name) for block in parameters.blocks if block.name != GAIN_SCALE}
    return dataclasses.replace(body, **fields) if fields else body

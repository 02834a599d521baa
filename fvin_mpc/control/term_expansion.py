"""Rigid-body terms expanded to first order where a linearization reads them: the same Jacobian, cheaper.

A stage of the real-time iteration (:func:`fvin_mpc.control.linearization.unrolled_stage_function`) needs the step
``F(x, u)`` and its derivatives in all ``n_δ + m`` directions ``(δ, Δu)`` at ``δ = 0``. Differentiated as
written, every one of those directions runs through every term the step calls — a learned model's
networks ``J(q)``, ``∇U``, ``g`` at the step's start and again at its end — although each term depends on
a handful of numbers only (a rotation's 3 directions, the 6 of ``(x, q)``).

:class:`FirstOrderTerms` wraps the terms so that each call ``T(a)`` returns ``T(ā) + ∂T/∂a(ā) (a − ā)``,
``ā`` the call's arguments at ``δ = 0``. Its value and its first derivatives at ``δ = 0`` are the call's
own, so the step built on it has the same derivatives there, to rounding: the chain rule applied in the
other order. Each term is then differentiated along its own arguments, once; the stage's directions run
only through the step's algebra and the linear expansions. The step's value is never taken from the
expansion: the stage's gap comes from the model's own step (the same expression, the same bits).

So a learned stage (``c`` and ``[A B]``) takes fewer CasADi instructions (``tests/test_rti.py`` checks that they
fall and that the derivatives agree; the counts by scene: docs/c-controller.md, "Fewer operations, again"). The
closed forms' terms are cheaper than their expansions and are left as written (:data:`MIN_INSTRUCTIONS`).
"""

from __future__ import annotations

import inspect
from typing import Any, Iterator, Sequence

import casadi as ca

from fvin_mpc.core import s3


def _leaves(value: Any) -> list[Any]:
    """The CasADi scalars of a nested tuple/list of terms (numbers and ``None`` are constants)."""
    if isinstance(value, (tuple, list)):
        return [leaf for item in value for leaf in _leaves(item)]
    return [value] if isinstance(value, ca.SX) else []


def _replaced(value: Any, leaves: Iterator[Any]) -> Any:
    """``value`` with its CasADi scalars replaced, in order, by ``leaves``."""
    if isinstance(value, (tuple, list)):
        return type(value)(_replaced(item, leaves) for item in value)
    return next(leaves) if isinstance(value, ca.SX) else value


#: The name the terms protocols give a unit quaternion argument (:class:`~fvin_mpc.core.fvin.RigidBodyTerms`,
#: :class:`~fvin_mpc.core.fvin_r3s3.CombinedTerms`): its expansion needs the 3 directions along the sphere only.
QUATERNION_ARGUMENT = "q"
#: A term whose value takes fewer CasADi instructions than this is differentiated as written: its expansion
#: would cost more than it saves (every closed-form term of the built-in scenes; the learned ones take
#: hundreds to thousands).
MIN_INSTRUCTIONS = 100


def _tangent_basis(q: Sequence[Any]) -> list[tuple[Any, ...]]:
    """``(q ⊗ i, q ⊗ j, q ⊗ k) / |q|``: orthonormal and orthogonal to ``q`` — the directions ``q`` moves in, to first
    order, on its sphere (a measured state's quaternion may be off unit norm by its rounding, or more)."""
    norm = ca.sqrt(sum(component * component for component in q))
    units = ((0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    return [tuple(component / norm for component in s3.multiply(tuple(q), unit)) for unit in units]


def _cost(method: Any, args: tuple[Any, ...]) -> int:
    """CasADi instructions of ``method`` on fresh symbols in place of ``args``' CasADi scalars."""
    count = len(_leaves(args))
    fresh = ca.SX.sym("fresh", count)
    value = _leaves(method(*_replaced(args, iter([fresh[i] for i in range(count)]))))
    return ca.Function("term", [fresh], [ca.vertcat(*value)], {"cse": True, "allow_free": True}).n_instructions()


class _Coordinates:
    """One argument of a term call, moved about its value ``ā`` at the linearization point: the symbols the
    term is differentiated in (``local``, at ``origin`` there), the argument written in them, and the argument's
    own displacement in those coordinates (``coordinates``: what multiplies the slope)."""

    def __init__(self, argument: Any, point_of: Any, quaternion: bool, label: str) -> None:
        value = ca.vertcat(*_leaves(argument))
        point = point_of(value)
        size = value.shape[0]
        if quaternion:  # along the sphere's 3 tangent directions T = (q̄⊗i, q̄⊗j, q̄⊗k): η = Tᵀ(q − q̄)
            basis = _tangent_basis([point[i] for i in range(4)])
            self.local, self.origin = ca.SX.sym(label, 3), ca.DM.zeros(3)
            moved = [point[i] + sum(self.local[d] * basis[d][i] for d in range(3)) for i in range(4)]
            self.coordinates = ca.vertcat(*[sum((value[i] - point[i]) * basis[d][i] for i in range(4))
                                            for d in range(3)])
        else:
            self.local, self.origin = ca.SX.sym(label, size), point
            moved = [self.local[i] for i in range(size)]
            self.coordinates = value - point
        self.argument = _replaced(argument, iter(moved))


class FirstOrderTerms:
    """``terms`` (any terms object on the CasADi backend: pivoted or free, learned or closed form) whose
    methods return their first-order expansion about their arguments at ``perturbations = 0`` (module
    docstring). Attributes that are not methods, calls whose arguments do not depend on the perturbations and
    terms cheaper than :data:`MIN_INSTRUCTIONS` are the wrapped terms' own. An argument named ``q``
    (:data:`QUATERNION_ARGUMENT`) is a quaternion that keeps its norm: it is expanded along its sphere's 3 tangent
    directions, not its 4 components — first-order exact where the call's ``q`` stays on that sphere, as every
    ``q`` a step passes its terms does (the chart's retraction and the step's increment are rotations)."""

    def __init__(self, terms: Any, perturbations: Sequence[Any]) -> None:
        self._terms = terms
        self._perturbations = list(perturbations)
        self._zeros = [ca.DM.zeros(*symbol.shape) for symbol in self._perturbations]

    def _at_zero(self, expression: Any) -> Any:
        return ca.substitute([expression], self._perturbations, self._zeros)[0]

    def _moves(self, args: tuple[Any, ...]) -> bool:
        leaves = _leaves(args)
        return bool(leaves) and any(ca.depends_on(ca.vertcat(*leaves), symbol) for symbol in self._perturbations)

    def __getattr__(self, name: str) -> Any:
        method = getattr(self._terms, name)
        if not callable(method):
            return method
        try:
            parameters = list(inspect.signature(method).parameters)
        except (TypeError, ValueError):  # no signature to read: no argument is taken for a quaternion
            parameters = []

        def expanded(*args: Any) -> Any:
            if not self._moves(args) or _cost(method, args) < MIN_INSTRUCTIONS:
                return method(*args)
            moved = [None if not _leaves(arg) else
                     _Coordinates(arg, self._at_zero, position < len(parameters) and len(_leaves(arg)) == 4
                                  and parameters[position] == QUATERNION_ARGUMENT, f"{name}_{position}")
                     for position, arg in enumerate(args)]
            result = method(*[arg if move is None else move.argument for arg, move in zip(args, moved)])
            outputs = _leaves(result)
            if not outputs:
                return result
            moving = [move for move in moved if move is not None]
            value = ca.vertcat(*outputs)
            value_at, slope_at = ca.substitute([value, ca.jacobian(value, ca.vertcat(*(m.local for m in moving)))],
                                               [m.local for m in moving], [m.origin for m in moving])
            first_order = value_at + ca.mtimes(slope_at, ca.vertcat(*(m.coordinates for m in moving)))
            return _replaced(result, iter([first_order[i] for i in range(first_order.shape[0])]))

        return expanded

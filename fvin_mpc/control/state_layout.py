"""Where the quaternion sits in a controller's state: ``R^a × S³ × R^b``, one description for the
pivoted bodies and the free rigid body.

A pivoted body's state is ``(q, ω)`` (7 numbers, :mod:`fvin_mpc.core.state`): no component before
the quaternion, three after it. The R³ × S³ state of :mod:`fvin_mpc.core.fvin_r3s3` is
``(x, q, v, ω)`` (13 numbers): three before, six after. In both the body-frame ``ω`` is the last
three entries, and everything after the quaternion is a *rate* (what a control changes within one
step: ``ω``, or ``v`` and ``ω``). The real-time MPC (:mod:`fvin_mpc.control.rti`) measures a state
against a linearization point in local coordinates of ``a + 3 + b`` numbers: the Euclidean parts
by difference, the quaternion in a chart of S³.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fvin_mpc.core.state import UNIT_NORM_TOLERANCE, as_float_array


@dataclass(frozen=True)
class StateLayout:
    """A state ``(e_before (a), q (4), e_after (b))``; the last three entries of ``e_after`` are ``ω``.

    Attributes:
        before: ``a``, Euclidean entries before the quaternion (0 pivoted, 3 free: ``x``).
        after: ``b``, Euclidean entries after it (3 pivoted: ``ω``; 6 free: ``v``, ``ω``).
        name: a label for messages.
    """

    before: int
    after: int
    name: str

    # Index facts, computed once (a measured state is sliced by them on every controller call).
    state_dim: int = field(init=False)
    #: entries of the local coordinates ``δ``: the quaternion's 3 chart coordinates and the rest
    tangent_dim: int = field(init=False)
    #: the quaternion's entries in a state
    quaternion: slice = field(init=False)
    #: the entries after the quaternion in a state (``ω``, or ``v`` and ``ω``)
    rates: slice = field(init=False)
    #: ``ω`` in a state (its last three entries)
    omega: slice = field(init=False)
    #: the quaternion's 3 chart coordinates in ``δ``
    chart: slice = field(init=False)
    #: ``ω``'s entries in ``δ`` (its last three)
    tangent_omega: slice = field(init=False)

    def __post_init__(self) -> None:
        n, a = self.before + 4 + self.after, self.before
        facts = {"state_dim": n, "tangent_dim": n - 1, "quaternion": slice(a, a + 4), "rates": slice(a + 4, n),
                 "omega": slice(n - 3, n), "chart": slice(a, a + 3), "tangent_omega": slice(n - 4, n - 1)}
        for name, value in facts.items():
            object.__setattr__(self, name, value)

    def check(self, x: Any) -> np.ndarray:
        """A measured state as a float64 copy with a unit quaternion (the policy of
        :func:`fvin_mpc.core.state.check_state`, for any layout).

        Raises:
            ValueError: wrong shape, NaN/inf, or a quaternion further than ``UNIT_NORM_TOLERANCE``
                from unit norm.
        """
        x = as_float_array(x, (self.state_dim,), f"state ({self.name})")
        norm = float(np.linalg.norm(x[self.quaternion]))
        if abs(norm - 1.0) > UNIT_NORM_TOLERANCE:
            raise ValueError(f"q is not a unit quaternion (|q| = {norm:.6g}; tolerance {UNIT_NORM_TOLERANCE})")
        x[self.quaternion] /= norm
        return x


#: A body on a fixed pivot: ``(q, ω)``.
PIVOTED = StateLayout(before=0, after=3, name="(q, ω)")
#: A free rigid body in R³ × S³: ``(x, q, v, ω)``.
FREE_BODY = StateLayout(before=3, after=6, name="(x, q, v, ω)")


def layout_of(state_dim: int) -> StateLayout:
    """The layout of states with ``state_dim`` entries (7 or 13)."""
    for layout in (PIVOTED, FREE_BODY):
        if layout.state_dim == state_dim:
            return layout
    raise ValueError(f"no state layout with {state_dim} entries (7: (q, ω); 13: (x, q, v, ω))")

"""What a scene's goal is: a small value the scene declares (:class:`~fvin_mpc.envs.scenes.SceneSpec`) and
controllers read. It sits in ``core`` because both envs and the control problem read it.

The configuration space says what a state is; the goal set says which states count as the goal — the
task's business (dm_control's Physics/Task split), never a flag on the space:

* :data:`UPRIGHT` — a pivot's goal: the body's attitude at one orientation (either sign of ``q``), every
  rate zero. The goal is given as that orientation ``(w, x, y, z)``; the controllers may add the energy
  deficit to it (its energy is the potential's maximum).
* :data:`HOVER` — a craft's goal: a whole state (a hover point), given as that state.

:func:`default_goal_set` is the rule a scene uses when it declares none: a body on a free joint hovers,
any other holds its attitude upright.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fvin_mpc.core.blocks import FreeJoint, StateLayout
from fvin_mpc.core.state import unit_quaternion


@dataclass(frozen=True, eq=False)
class GoalSet:
    """A kind of goal (module docstring); the two values are singletons, compare them with ``is``.

    Attributes:
        name: a short tag (``"upright"``, ``"hover"``), e.g. in reports.
        description: a few words for messages.
        attitude_at_rest: the goal is one attitude at rest, given as its orientation; else a whole state.
    """

    name: str
    description: str
    attitude_at_rest: bool

    def goal_state(self, layout: StateLayout, goal: Any) -> np.ndarray:
        """The goal as a state of ``layout``: for :data:`UPRIGHT` the orientation ``goal`` (normalized) in the
        state's one attitude, every other entry zero; for :data:`HOVER` ``goal`` itself, checked.

        Raises:
            ValueError: ``goal`` is not an orientation (upright) or a state of ``layout`` (hover), or the
                layout has no single attitude to hold upright.
        """
        if not self.attitude_at_rest:
            return layout.check(goal)
        state = np.zeros(layout.state_dim)
        state[layout.attitude(by=f"the {self.name} goal").quaternion] = unit_quaternion(goal, "goal")
        return state

    def __repr__(self) -> str:
        return f"GoalSet({self.name!r})"


#: A pivot's goal set: one orientation of the body's attitude (either sign), at rest.
UPRIGHT = GoalSet("upright", "a pivot's upright orientation, at rest", attitude_at_rest=True)
#: A craft's goal: a whole state, its hover point.
HOVER = GoalSet("hover", "a craft's hover point (a whole state)", attitude_at_rest=False)


def default_goal_set(layout: StateLayout) -> GoalSet:
    """The goal set of a body whose scene declares none: :data:`HOVER` on a free joint, else :data:`UPRIGHT`."""
    return HOVER if any(isinstance(block, FreeJoint) for block in layout.blocks) else UPRIGHT

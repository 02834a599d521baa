"""Controller presets of the built-in scenes: the few MPC settings a scene changes from the defaults
its own scales give (:func:`fvin_mpc.control.scene.default_mpc_settings`), each with its reason.

Scenes declare physics, task and space (:mod:`fvin_mpc.envs.scenes`); how to control them lives
here. A scene given by its MJCF path gets no preset — the scale-derived defaults only — even when
its name is a built-in's: a preset was measured on the built-in body, not on a user's.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Mapping

from fvin_mpc.control.mpc import IpoptOptions, RTIOptions
from fvin_mpc.envs.scenes import SceneSpec, built_in_scene


@dataclass(frozen=True)
class Preset:
    """What a built-in scene changes in its :class:`~fvin_mpc.control.mpc.MPCSettings`.

    Attributes:
        settings: problem fields for every solver.
        per_solver: further problem fields when one solver solves (``{"ipopt": {...}, "rti": {...}}``),
            applied after ``settings`` (a real-time iteration may want a shorter horizon than IPOPT).
        ipopt: the solvers to convergence's options (:class:`~fvin_mpc.control.mpc.IpoptOptions`),
            ``None`` for the defaults; applied whatever the solver (the RTI's cold solve may be IPOPT's).
        rti: the real-time iteration's options (:class:`~fvin_mpc.control.mpc.RTIOptions`), ``None`` for
            the defaults; applied when the RTI solves.
        reasons: why, one sentence per change, each naming the ``docs/`` page with the numbers.
    """

    settings: Mapping[str, Any] = field(default_factory=dict)
    per_solver: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    ipopt: IpoptOptions | None = None
    rti: RTIOptions | None = None
    reasons: tuple[str, ...] = ()

    def fields_for(self, solver: str) -> dict[str, Any]:
        """What this preset sets when ``solver`` solves (for :meth:`MPCSettings.updated`): the IPOPT options
        always (the RTI's cold solve may be IPOPT's), the RTI's only when it solves — as the fields it
        changes from :class:`RTIOptions`' defaults, so that what the scene's scales set (its
        ``restart_speed``) stays."""
        options: dict[str, Any] = {} if self.ipopt is None else {"ipopt": self.ipopt}
        if solver == "rti" and self.rti is not None:
            default = RTIOptions()
            options["rti"] = {f.name: getattr(self.rti, f.name) for f in fields(RTIOptions)
                              if getattr(self.rti, f.name) != getattr(default, f.name)}
        return {**self.settings, **self.per_solver.get(solver, {}), **options}


PRESETS: dict[str, Preset] = {
    "pendulum": Preset(
        per_solver={"rti": {"horizon": 20}},
        rti=RTIOptions(dynamics="implicit"),
        reasons=(
            "RTI horizon 20: one Gauss–Newton step per period follows a shorter plan more closely (mean cost "
            "148.6 at N = 20 against 176.1 at N = 30 over 50 starts; docs/bench/rti.md).",
            "RTI implicit dynamics: the learned terms once per node, the period's time within 1.5× the closed "
            "form's (docs/realtime.md).",
        )),
    "pendulum_damped": Preset(
        settings={"horizon": 50},
        per_solver={"ipopt": {"terminal_energy_weight": 0.0}},
        reasons=(
            "Horizon 2.5 s: at 1.5 and 2 s the plan settles on a local optimum that never swings up, learned and "
            "closed form alike (docs/scenes.md).",
            "IPOPT without the terminal energy term: the 2.5 s horizon sees the goal, and the settings were "
            "measured so (docs/scenes.md).",
        )),
    "spherical_pendulum": Preset(
        settings={"horizon": 50},
        per_solver={"ipopt": {"terminal_energy_weight": 0.0}, "rti": {"omega_weight": 0.06}},
        ipopt=IpoptOptions(max_iter=300),
        rti=RTIOptions(max_iter=3, budget_s=0.006),
        reasons=(
            "Horizon 2.5 s and 300 IPOPT iterations: 1.5 N·m against 6 N·m of gravity torque needs several pumps, "
            "and cold solves from rest take about 130 iterations (docs/spherical.md).",
            "IPOPT without the terminal energy term: on a ball joint the energy can sit in a conical swing "
            "(docs/spherical.md); the RTI keeps it, without it the closed form never swung up (docs/realtime.md).",
            "RTI up to three iterations within 6 ms: with one, the learned model reached the top but often "
            "missed the catch (docs/realtime.md).",
            "RTI stage ω weight 0.06 instead of the scaled 0.129: the catch settles in 0.70 s instead of 1.05 s, "
            "80/80 held over 20 starts × four latencies (docs/realtime.md).",
        )),
}


def preset_for(spec: SceneSpec) -> Preset:
    """The preset of a built-in scene's declaration; an empty one for any other scene."""
    return PRESETS.get(spec.name, Preset()) if built_in_scene(spec) else Preset()

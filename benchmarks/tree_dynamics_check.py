"""The closed form of a kinematic tree against MuJoCo over the mechanism family: one row per member.

``python -m benchmarks.tree_dynamics_check`` evaluates :class:`fvin_mpc.core.tree_dynamics.KinematicTree` on
every member of :mod:`fvin_mpc.envs.mechanism_family` (by default its ``MEMBERS``: seeds 0, 1, 2 of every
kind) at random states and prints, per member, the largest absolute difference from MuJoCo's ``mj_fullM``,
``qfrc_bias``, ``qfrc_passive``, ``actuator_moment`` and energy, and the largest difference between the CasADi
form (an SX function, evaluated) and the NumPy one — a Markdown table (``docs/mechanisms.md`` shows it).
"""

from __future__ import annotations

import argparse
import time
from typing import Sequence

import casadi
import mujoco
import numpy as np

from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.tree_dynamics import KinematicTree
from fvin_mpc.envs.mechanism_family import (
    KINDS,
    MEMBERS,
    TERMS,
    closed_form_errors,
    mechanism_mjcf,
    random_joint_states,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.tree_dynamics_check",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=None,
                        help="the first seed of each kind (with --seeds; default: the family's MEMBERS)")
    parser.add_argument("--seeds", type=int, default=3, help="how many seeds of each kind from --seed (default 3)")
    parser.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS), help="the kinds (default: all)")
    parser.add_argument("--states", type=int, default=10, help="random states per member (default 10)")
    parser.add_argument("--no-casadi", action="store_true", help="leave out the CasADi column")
    parser.add_argument("--summary", action="store_true", help="print the largest error of each term only")
    return parser


def casadi_difference(model: mujoco.MjModel, seed: int, states: int) -> float:
    """The largest difference between the CasADi form (every term of :meth:`KinematicTree.terms` in one SX
    function, evaluated) and the NumPy one, relative to the term's scale where that is above 1."""
    tree, ops = KinematicTree.from_mujoco(model), get_ops("casadi")
    qpos_symbol, qvel_symbol = casadi.SX.sym("qpos", tree.nq), casadi.SX.sym("qvel", tree.nv)
    terms = tree.terms(ops.unstack(qpos_symbol), ops.unstack(qvel_symbol), ops)
    flat = [*(e for row in terms.mass for e in row), *terms.bias, *terms.passive,
            *(e for row in terms.moment for e in row)]
    function = casadi.Function("terms", [qpos_symbol, qvel_symbol], [ops.stack(flat)])
    qpos, qvel = random_joint_states(model, np.random.default_rng(seed), states)
    arrays = tree.numpy_terms(qpos, qvel)
    expected = np.concatenate([arrays[name].reshape(states, -1) for name in ("mass", "bias", "passive", "moment")],
                              axis=1)
    worst = 0.0
    for i in range(states):
        value = np.asarray(function(qpos[i], qvel[i])).ravel()
        worst = max(worst, float(np.max(np.abs(value - expected[i]) / np.maximum(1.0, np.abs(expected[i])))))
    return worst


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    members = [m for m in MEMBERS if m[0] in args.kinds] if args.seed is None else \
        [(kind, seed) for kind in args.kinds for seed in range(args.seed, args.seed + args.seeds)]
    columns = [f"max abs {name}" for name in TERMS] + ([] if args.no_casadi else ["CasADi − NumPy (rel.)"])
    if not args.summary:
        print("| member | joints | nv | nu | " + " | ".join(columns) + " | min eig M |")
        print("|---" * (5 + len(columns)) + "|")
    worst = dict.fromkeys(columns, 0.0)
    started = time.perf_counter()
    for kind, seed in members:
        model = mujoco.MjModel.from_xml_string(mechanism_mjcf(kind, seed))
        found = closed_form_errors(model, seed, args.states)
        values = [found["error"][name] for name in TERMS]
        if not args.no_casadi:
            values.append(casadi_difference(model, seed, min(args.states, 3)))
        worst = {column: max(worst[column], value) for column, value in zip(columns, values)}
        joints = "+".join(mujoco.mjtJoint(int(t)).name[6:].lower() for t in model.jnt_type)
        if not args.summary:
            print(f"| {kind} {seed} | {joints} | {model.nv} | {model.nu} | "
                  + " | ".join(f"{value:.1e}" for value in values) + f" | {found['mass']['smallest_eigenvalue']:.2g} |")
    print(f"\n{len(members)} members × {args.states} states in {time.perf_counter() - started:.1f} s; largest: "
          + ", ".join(f"{column} {value:.1e}" for column, value in worst.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

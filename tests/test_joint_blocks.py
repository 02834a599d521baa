"""A MuJoCo model's joints as blocks (:func:`fvin_mpc.envs.joint_blocks.joint_layout`): a state of the blocks
is MuJoCo's ``(qpos, qvel)``, so MuJoCo is the oracle without conversions — its kinetic energy is
``½ νᵀ M(q) ν`` with ``M = mj_fullM`` and ``ν`` the blocks' rates, and a retraction along ``qvel·dt`` is
``mj_integratePos`` to second order."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from fvin_mpc.core.blocks import Ball, FreeJoint, Hinge, Slide
from fvin_mpc.envs.joint_blocks import joint_layout

#: A tree of every joint kind: a free base carrying a cart on a rail (slide), a pole on it (hinge) and a
#: ball-jointed second link, with armature on the hinge (it enters M(q)).
TREE = """
<mujoco>
  <option><flag energy="enable"/></option>
  <worldbody>
    <body name="base">
      <freejoint name="root"/>
      <geom type="box" size="0.2 0.1 0.05" mass="2"/>
      <body name="cart" pos="0.1 0 0">
        <joint name="rail" type="slide" axis="1 0 0"/>
        <geom type="box" size="0.05 0.05 0.05" mass="0.5"/>
        <body name="pole" pos="0 0 0.05">
          <joint name="pivot" type="hinge" axis="0 1 0" armature="0.01"/>
          <geom type="capsule" fromto="0 0 0 0 0 0.4" size="0.02" mass="0.3"/>
          <body name="link" pos="0 0 0.4">
            <joint name="shoulder" type="ball"/>
            <geom type="capsule" fromto="0 0 0 0.1 0 0.3" size="0.02" mass="0.2"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def tree():
    return mujoco.MjModel.from_xml_string(TREE)


def _random_joint_state(model, rng):
    data = mujoco.MjData(model)
    qpos = rng.normal(size=model.nq)
    for joint in range(model.njnt):
        start = model.jnt_qposadr[joint]
        if model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_FREE:
            qpos[start + 3:start + 7] /= np.linalg.norm(qpos[start + 3:start + 7])
        elif model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_BALL:
            qpos[start:start + 4] /= np.linalg.norm(qpos[start:start + 4])
    data.qpos[:], data.qvel[:] = qpos, rng.normal(size=model.nv)
    return data


def test_the_blocks_follow_the_tree_and_its_joints_sizes(tree):
    layout = joint_layout(tree)
    assert [type(block) for block in layout.blocks] == [FreeJoint, Slide, Hinge, Ball]
    assert [block.label for block in layout.blocks] == ["root", "rail", "pivot", "shoulder"]
    assert layout.positions.stop == tree.nq and layout.state_dim == tree.nq + tree.nv
    assert layout.tangent_dim == 2 * tree.nv
    assert [q.start for q in layout.quaternions] == [3, 9]


def test_a_state_is_qpos_and_qvel_and_mujoco_is_the_oracle_of_its_kinetic_energy(tree):
    layout, rng = joint_layout(tree), np.random.default_rng(0)
    for _ in range(5):
        data = _random_joint_state(tree, rng)
        x = layout.from_joints(data.qpos, data.qvel)
        np.testing.assert_allclose(layout.qpos(x), data.qpos, rtol=0, atol=1e-15)  # quaternions renormalized
        np.testing.assert_array_equal(layout.qvel(x), data.qvel)
        mujoco.mj_forward(tree, data)
        mass = np.zeros((tree.nv, tree.nv))
        mujoco.mj_fullM(tree, data, mass)
        rates = layout.qvel(x)
        assert 0.5 * rates @ mass @ rates == pytest.approx(float(data.energy[1]), rel=1e-12)


def test_a_retraction_along_qvel_is_mujocos_integration_to_second_order(tree):
    """``retract(x, δ)`` with each chart coordinate ``qvel·dt`` over its block's chart scale against
    ``mj_integratePos``: the positions agree to ``O(dt²)`` (error ratio ~4 when ``dt`` halves; exact for the
    slide and the hinge)."""
    layout, rng = joint_layout(tree), np.random.default_rng(1)
    data = _random_joint_state(tree, rng)
    x = layout.from_joints(data.qpos, data.qvel)
    scales = np.array([s for block in layout.blocks for s in block.chart_scales])
    errors = []
    for dt in (1e-2, 5e-3):
        delta = np.zeros(layout.tangent_dim)
        delta[:tree.nv] = data.qvel * dt / scales
        moved = layout.retract(x, delta)
        integrated = data.qpos.copy()
        mujoco.mj_integratePos(tree, integrated, data.qvel, dt)
        errors.append(np.abs(layout.qpos(moved) - integrated).max())
        for slot in layout.slots:
            if isinstance(slot.block, (Slide, Hinge)):
                np.testing.assert_allclose(layout.qpos(moved)[slot.position], integrated[slot.position], atol=1e-15)
    assert errors[1] < errors[0] / 3.0, errors


def test_a_model_without_joints_is_refused():
    with pytest.raises(ValueError, match="no joints"):
        joint_layout(mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>"))


def test_a_hinge_block_is_wrap_free_on_every_backend():
    """A hinge's chart is the difference on the circle and its distance ``sin²(Δθ/2)``: a turn apart is no
    apart, across ±π the short way round; NumPy, torch and CasADi give the same numbers."""
    import casadi as ca
    import torch

    from fvin_mpc.core.backend import get_ops
    from fvin_mpc.core.blocks import StateLayout

    layout = StateLayout((Hinge(label="a"), Slide(label="b")), name="(θ, s, θ̇, ṡ)")
    assert (layout.state_dim, layout.tangent_dim, layout.angular_rates) == (4, 4, slice(2, 3))
    base = np.array([np.pi - 0.1, 0.3, 1.0, -2.0])
    there = np.array([-np.pi + 0.1 + 4 * np.pi, 0.5, 1.5, -2.5])  # two turns on and across ±π
    delta = layout.local(base, there)
    np.testing.assert_allclose(delta, [0.2, 0.2, 0.5, -0.5], atol=1e-12)
    np.testing.assert_allclose(layout.local(base, layout.retract(base, delta)), delta, atol=1e-12)
    assert layout.distance(there, base) == pytest.approx(np.sin(0.1) ** 2 + 0.04, abs=1e-12)
    for ops, convert, back in ((get_ops("torch"), torch.as_tensor, lambda t: t.numpy()),
                               (get_ops("casadi"), ca.DM, lambda d: np.asarray(ca.evalf(d)).ravel())):
        np.testing.assert_allclose(back(layout.local(convert(base), convert(there), ops)), delta, atol=1e-14)
        assert np.asarray(back(layout.distance(convert(there), convert(base), ops))).reshape(-1)[0] == \
            pytest.approx(float(layout.distance(there, base)), abs=1e-14)

"""The closed form of a kinematic tree (:class:`fvin_mpc.core.tree_dynamics.KinematicTree`) against MuJoCo:
``M(q)`` = ``mj_fullM``, the bias = ``qfrc_bias``, the passive force = ``qfrc_passive``, the actuator moment =
``actuator_moment`` (dense) to 1e-9 at random states — on a tree of every joint kind and transmission, and
on every member of the seeded mechanism family (:mod:`fvin_mpc.envs.mechanism_family`) — and the CasADi
form, evaluated, equal to the NumPy one to 1e-12 (the same source)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from test_joint_blocks import TREE as CONTACTS_ON

from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.errors import SceneError
from fvin_mpc.core.tree_dynamics import KinematicTree, refusals
from fvin_mpc.envs.joint_blocks import joint_layout
from fvin_mpc.envs.mechanism_family import (
    KINDS,
    MEMBERS,
    TERMS,
    closed_form_errors,
    mechanism_mjcf,
    mechanism_scene,
    mujoco_terms,
    random_joint_states,
)

NP = get_ops("numpy")
#: MuJoCo agreement, relative to the largest entry of MuJoCo's value where that is above 1.
TOLERANCE = 1e-9
#: CasADi (evaluated) against NumPy: the same arithmetic.
SAME_SOURCE = 1e-12
STATES = 10

#: Every joint kind (free base, slide, hinge, ball), two hinges in one body, a ball and a slide in one, joint
#: offsets, ``ref`` and springs, an explicit full inertia, gravity off the vertical, and every transmission
#: supported: joint on a slide, hinge, ball and free joint, jointinparent on a ball and a free joint, sites'
#: wrenches, an actuator of gain 2.
TREE = """
<mujoco>
  <option gravity="0.3 -0.2 -9.81"><flag contact="disable" energy="enable"/></option>
  <worldbody>
    <body name="base" pos="0.2 0.1 1" quat="0.9 0.1 0.3 0.2">
      <freejoint name="root"/>
      <geom type="box" size="0.2 0.1 0.05" mass="2"/>
      <body name="cart" pos="0.1 0 0" quat="1 0.2 0 0.1">
        <joint name="rail" type="slide" axis="1 0.2 0" damping="0.3" armature="0.02" stiffness="2" springref="0.1"
               ref="0.05"/>
        <geom type="box" size="0.05 0.05 0.05" mass="0.5" pos="0.01 0.02 0"/>
        <body name="pole" pos="0 0 0.05">
          <joint name="pivot" type="hinge" axis="0 1 0.3" pos="0.01 0 -0.02" armature="0.01" damping="0.05"
                 stiffness="0.7" ref="0.3" springref="-0.2"/>
          <geom type="capsule" fromto="0 0 0 0 0.05 0.4" size="0.02" mass="0.3"/>
          <body name="link" pos="0 0 0.4" quat="0.8 0 0.6 0">
            <joint name="shoulder" type="ball" pos="0.02 -0.01 0.03" damping="0.02" armature="0.003"/>
            <geom type="capsule" fromto="0 0 0 0.1 0 0.3" size="0.02" mass="0.2"/>
            <site name="tip" pos="0.1 0.02 0.3" quat="0.7 0.1 0.7 0"/>
            <body name="wrist" pos="0.1 0 0.3">
              <joint name="wrist_a" type="hinge" axis="1 0 0" damping="0.01"/>
              <joint name="wrist_b" type="hinge" axis="0 0 1" pos="0 0.02 0"/>
              <inertial pos="0.03 0.01 0.05" mass="0.15" fullinertia="0.002 0.003 0.0025 0.0003 -0.0002 0.0001"/>
            </body>
          </body>
        </body>
      </body>
      <body name="side" pos="-0.2 0 0">
        <joint name="side_ball" type="ball" pos="0 0 0.01"/>
        <joint name="side_slide" type="slide" axis="0 0 1"/>
        <geom type="sphere" size="0.05" pos="0 0.1 0" mass="0.4"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="rail" gear="2.5"/>
    <motor joint="pivot" gear="-1.5"/>
    <motor joint="shoulder" gear="0.3 -0.7 1.1 0 0 0"/>
    <general jointinparent="shoulder" gear="0.5 0.2 -0.4 0 0 0" gainprm="2"/>
    <motor site="tip" gear="0.1 0.2 0.3 0.4 -0.5 0.6"/>
    <motor joint="root" gear="1 2 3 4 5 6"/>
    <motor jointinparent="root" gear="1 -2 0.5 0.4 0.3 -0.2"/>
    <motor site="tip" gear="0 0 1 0 0 0"/>
  </actuator>
</mujoco>
"""


def assert_equals_mujoco(model: mujoco.MjModel, seed: int) -> None:
    """The closed form at ``STATES`` random states against MuJoCo (``closed_form_errors``), each term to
    ``TOLERANCE`` relative to its scale where that is above 1; ``M`` symmetric positive definite."""
    found = closed_form_errors(model, seed, STATES)
    for name in TERMS:
        assert found["error"][name] <= TOLERANCE * max(1.0, found["scale"][name]), (name, found)
    assert found["mass"]["asymmetry"] == 0.0 and found["mass"]["smallest_eigenvalue"] > 0.0, found["mass"]


@pytest.fixture(scope="module")
def tree_model():
    return mujoco.MjModel.from_xml_string(TREE)


def test_the_tree_of_every_joint_kind_equals_mujoco(tree_model):
    tree = KinematicTree.from_mujoco(tree_model)
    kinds = ["free", "slide", "hinge", "ball", "hinge", "hinge", "ball", "slide"]
    assert [joint.kind for joint in tree.joints] == kinds
    assert {a.transmission for a in tree.actuators} == {"joint", "jointinparent", "site"}
    assert tree.gains()[3] == 2.0
    assert_equals_mujoco(tree_model, seed=0)


@pytest.mark.parametrize("kind, seed", MEMBERS, ids=[f"{kind}-{seed}" for kind, seed in MEMBERS])
def test_every_family_member_equals_mujoco(kind, seed):
    assert_equals_mujoco(mujoco.MjModel.from_xml_string(mechanism_mjcf(kind, seed)), seed)


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_a_hundred_members_of_each_kind_equal_mujoco(kind):
    for seed in range(3, 103):
        assert_equals_mujoco(mujoco.MjModel.from_xml_string(mechanism_mjcf(kind, seed)), seed)


def test_with_gravity_damping_and_springs_disabled_the_terms_follow_the_flags(tree_model):
    text = TREE.replace('<flag contact="disable" energy="enable"/>',
                        '<flag contact="disable" energy="enable" gravity="disable" damper="disable" spring="disable"/>')
    model = mujoco.MjModel.from_xml_string(text)
    tree = KinematicTree.from_mujoco(model)
    assert tree.gravity == (0.0, 0.0, 0.0) and not any(tree.damping) and not tree.springs
    assert_equals_mujoco(model, seed=1)


# ----------------------------------------------------------------------------- one source, every backend
def casadi_function(tree: KinematicTree):
    """The four terms as one CasADi SX function of ``(qpos, qvel)``, from the same code as NumPy's."""
    casadi = pytest.importorskip("casadi")
    ops = get_ops("casadi")
    qpos, qvel = casadi.SX.sym("qpos", tree.nq), casadi.SX.sym("qvel", tree.nv)
    terms = tree.terms(ops.unstack(qpos), ops.unstack(qvel), ops)

    def matrix(rows):
        return casadi.vertcat(*[casadi.horzcat(*row) for row in rows]) if rows else casadi.DM(0, tree.nv)

    return casadi.Function("tree_terms", [qpos, qvel], [matrix(terms.mass), casadi.vertcat(*terms.bias),
                                                        casadi.vertcat(*terms.passive), matrix(terms.moment)])


@pytest.mark.parametrize("source", ["tree", *(f"{kind}-{seed}" for kind, seed in MEMBERS)])
def test_the_casadi_form_evaluated_equals_numpy(source, tree_model):
    if source == "tree":
        model = tree_model
    else:
        kind, seed = source.rsplit("-", 1)
        model = mujoco.MjModel.from_xml_string(mechanism_mjcf(kind, int(seed)))
    tree = KinematicTree.from_mujoco(model)
    function = casadi_function(tree)
    qpos, qvel = random_joint_states(model, np.random.default_rng(2), 3)
    ours = tree.numpy_terms(qpos, qvel)
    for i in range(3):
        values = [np.array(value) for value in function(qpos[i], qvel[i])]
        for name, value in zip(("mass", "bias", "passive", "moment"), values):
            expected = ours[name][i]
            scale = max(1.0, float(np.max(np.abs(expected), initial=0.0)))
            np.testing.assert_allclose(value.reshape(expected.shape), expected, rtol=0, atol=SAME_SOURCE * scale)


def test_the_torch_form_equals_numpy(tree_model):
    torch = pytest.importorskip("torch")
    tree, ops = KinematicTree.from_mujoco(tree_model), get_ops("torch")
    qpos, qvel = random_joint_states(tree_model, np.random.default_rng(3), 4)
    terms = tree.terms(ops.unstack(torch.tensor(qpos)), ops.unstack(torch.tensor(qvel)), ops)
    mass = np.stack([np.stack([np.broadcast_to(torch.as_tensor(entry, dtype=torch.float64).numpy(), (4,))
                               for entry in row], axis=-1) for row in terms.mass], axis=-2)
    np.testing.assert_allclose(mass, tree.numpy_terms(qpos, qvel)["mass"], rtol=0, atol=1e-12)


def test_the_rates_are_the_joint_blocks_rates(tree_model):
    """The closed form's coordinates are the blocks' (``envs.joint_blocks``): a state's rates are its ``qvel``,
    and ``½ νᵀ M ν`` is the kinetic energy."""
    layout, tree = joint_layout(tree_model), KinematicTree.from_mujoco(tree_model)
    qpos, qvel = random_joint_states(tree_model, np.random.default_rng(4), 1)
    x = layout.from_joints(qpos[0], qvel[0])
    mass = tree.numpy_terms(layout.qpos(x), layout.qvel(x))["mass"]
    rates = layout.qvel(x)
    assert 0.5 * rates @ mass @ rates == pytest.approx(mujoco_terms(tree_model, qpos[0], qvel[0])["kinetic"], rel=1e-12)


# ----------------------------------------------------------------------------- refusals
SIMPLE = """
<mujoco>
  <option><flag contact="disable"/></option>
  <worldbody>
    <body name="a"><joint name="j" type="{kind}" {joint}/><geom size="0.1" pos="0 0 -0.5" mass="1"/>
      <site name="s" pos="0 0 -0.5"/><site name="r"/>
    </body>
  </worldbody>
  {extra}
</mujoco>
"""


@pytest.mark.parametrize("kind, joint, extra, expected", [
    ("hinge", "", '<tendon><fixed name="t"><joint joint="j" coef="1"/></fixed></tendon>', "tendons"),
    ("hinge", "", '<equality><joint joint1="j"/></equality>', "equality constraints"),
    ("hinge", 'frictionloss="0.1"', "", "dry friction"),
    ("ball", 'stiffness="1"', "", "springs on ball or free joints"),
    ("hinge", "", '<actuator><position joint="j" kp="2"/></actuator>', "actuators with bias"),
    ("hinge", "", '<actuator><motor site="s" refsite="r" gear="1 0 0 0 0 0"/></actuator>', "reference site"),
    ("hinge", "", '<actuator><motor joint="j" forcerange="-1 1"/></actuator>', "force range"),
    ("hinge", "", '<option density="1.2"/>', "fluid forces"),
])
def test_what_the_closed_form_leaves_out_is_refused_in_one_line(kind, joint, extra, expected):
    model = mujoco.MjModel.from_xml_string(SIMPLE.format(kind=kind, joint=joint, extra=extra))
    assert any(expected in problem for problem in refusals(model))
    with pytest.raises(SceneError, match=expected) as caught:
        KinematicTree.from_mujoco(model)
    assert "\n" not in str(caught.value)


def test_contacts_are_refused_unless_disabled():
    """``tests/test_joint_blocks.py``'s tree leaves contacts on: refused; the same with them disabled is not."""
    assert any("contacts" in problem for problem in refusals(mujoco.MjModel.from_xml_string(CONTACTS_ON)))
    off = CONTACTS_ON.replace('<flag energy="enable"/>', '<flag energy="enable" contact="disable"/>')
    assert refusals(mujoco.MjModel.from_xml_string(off)) == []
    assert_equals_mujoco(mujoco.MjModel.from_xml_string(off), seed=5)


# ----------------------------------------------------------------------------- the family
def test_the_family_is_seeded_and_its_members_are_what_it_says():
    assert mechanism_mjcf("furuta", 5) == mechanism_mjcf("furuta", 5)
    assert mechanism_mjcf("furuta", 5) != mechanism_mjcf("furuta", 6)
    kinds, transmissions, actuation = set(), set(), set()
    for kind, seed in MEMBERS:
        text, facts = mechanism_scene(kind, seed)
        model = mujoco.MjModel.from_xml_string(text)
        assert facts["kind"] == kind and facts["seed"] == seed
        assert 2 <= model.njnt <= 4 and model.nu >= 1 and refusals(model) == []
        assert model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        assert model.opt.enableflags & int(mujoco.mjtEnableBit.mjENBL_ENERGY)
        kinds |= {int(t) for t in model.jnt_type}
        transmissions |= {int(t) for t in model.actuator_trntype}
        actuation.add(facts.get("actuation"))
    joint = mujoco.mjtJoint
    assert kinds == {int(joint.mjJNT_HINGE), int(joint.mjJNT_SLIDE), int(joint.mjJNT_BALL)}
    assert transmissions == {int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT),
                             int(mujoco.mjtTrn.mjTRN_SITE)}
    assert {"pendubot", "acrobot", "full"} <= actuation
    with pytest.raises(ValueError, match="unknown mechanism kind"):
        mechanism_mjcf("hexapod", 0)

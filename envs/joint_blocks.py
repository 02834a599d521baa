"""A MuJoCo model's joints as the blocks of a state (:mod:`fvin_mpc.core.blocks`), in the tree's order.

Each block's position and rate are its joint's ``qpos`` and ``qvel`` entries, so a state of these blocks is
MuJoCo's ``(qpos, qvel)`` and the model's joint-space quantities — ``mj_fullM``, ``qfrc_bias``,
``qfrc_passive``, ``actuator_moment`` — apply to its rates as they are (``../shared/DESIGN.md``, "Mechanisms").
"""

from __future__ import annotations

import mujoco

from fvin_mpc.core.blocks import Ball, Block, FreeJoint, Hinge, Slide, StateLayout

_KINDS: dict[int, type[Block]] = {
    int(mujoco.mjtJoint.mjJNT_FREE): FreeJoint, int(mujoco.mjtJoint.mjJNT_BALL): Ball,
    int(mujoco.mjtJoint.mjJNT_SLIDE): Slide, int(mujoco.mjtJoint.mjJNT_HINGE): Hinge,
}


def joint_layout(model: mujoco.MjModel) -> StateLayout:
    """The blocks of ``model``'s joints, one per joint in MuJoCo's joint order (the kinematic tree's, depth
    first), each labelled with the joint's name.

    Raises:
        ValueError: a model with no joints, or whose joints' ``qpos``/``qvel`` addresses do not follow their
            order (MuJoCo lays them out so; anything else would break the identity of the maps).
    """
    if model.njnt == 0:
        raise ValueError("the model has no joints: no state to make blocks of")
    blocks, position, rate = [], 0, 0
    for joint in range(model.njnt):
        kind = _KINDS[int(model.jnt_type[joint])]
        label = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, joint) or f"joint {joint}"
        block = kind(label=label)
        if int(model.jnt_qposadr[joint]) != position or int(model.jnt_dofadr[joint]) != rate:
            raise ValueError(f"joint {label!r}: its qpos/qvel addresses do not follow the joints' order")
        blocks.append(block)
        position, rate = position + block.position_size, rate + block.tangent_size
    names = ", ".join(f"{block.label} ({block.kind})" for block in blocks)
    return StateLayout(tuple(blocks), name=f"(qpos, qvel) of {names}")

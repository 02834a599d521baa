"""Gymnasium environments over MuJoCo scenes, and the scenes' physics declarations.

Importing the package registers ``fvin_mpc/Pendulum-v0``, ``fvin_mpc/PendulumDamped-v0`` and
``fvin_mpc/SphericalPendulum-v0`` (see :func:`register_envs`).
"""

from .rigid_body_env import ENV_IDS, RigidBodyEnv, register_envs
from .scenes import SCENES, ScenePhysics, SceneSpec, build_model, get_scene, infer_physics

__all__ = [
    "ENV_IDS",
    "RigidBodyEnv",
    "SCENES",
    "ScenePhysics",
    "SceneSpec",
    "build_model",
    "get_scene",
    "infer_physics",
    "register_envs",
]

register_envs()

"""Gymnasium environments over MuJoCo scenes, and the scenes' physics declarations.

Importing the package registers ``fvin_mpc/Pendulum-v0``, ``fvin_mpc/PendulumDamped-v0``,
``fvin_mpc/SphericalPendulum-v0`` (:func:`register_envs`) and ``fvin_mpc/Quadrotor-v0``
(:func:`register_free_body_envs`).
"""

from .quadrotor_env import ENV_IDS as FREE_BODY_ENV_IDS
from .quadrotor_env import QuadrotorEnv
from .quadrotor_env import register_envs as register_free_body_envs
from .rigid_body_env import ENV_IDS, RigidBodyEnv, register_envs
from .scenes import FREE_BODY_SCENES, SCENES, ScenePhysics, SceneSpec, build_model, get_scene, infer_physics

__all__ = [
    "ENV_IDS",
    "FREE_BODY_ENV_IDS",
    "FREE_BODY_SCENES",
    "QuadrotorEnv",
    "RigidBodyEnv",
    "SCENES",
    "ScenePhysics",
    "SceneSpec",
    "build_model",
    "get_scene",
    "infer_physics",
    "register_envs",
    "register_free_body_envs",
]

register_envs()
register_free_body_envs()

"""A known constant torque disturbance on a scene, for offset-free control tests (the oracle).

``ConstantTorqueDisturbance(env, torque)`` wraps a :class:`~fvin_mpc.envs.RigidBodyEnv` and adds
``torque`` (the actuators' units: one entry per actuator) to the joint's generalized force through
MuJoCo's ``data.qfrc_applied`` on the degrees of freedom the actuators drive, before every step and
after every reset (``mj_resetData`` clears it). The actuators' own range limits the commanded
torque, not the disturbance. A controller whose model is ``x⁺ = F(x, u + d)`` should estimate
``d = torque``.

Deliberately exported from nowhere else (``import fvin_mpc.envs.disturbance``): no scene, command
or study applies it unasked.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np


class ConstantTorqueDisturbance(gymnasium.Wrapper):
    """Adds a constant torque ``(m,)`` (actuator units) to the plant at every MuJoCo sub-step.

    Raises:
        ValueError: ``torque`` has not one entry per actuator, is not finite, or an actuator's
            transmission is not a joint.
    """

    def __init__(self, env: Any, torque: Any) -> None:
        super().__init__(env)
        import mujoco

        model = env.unwrapped.model
        self.torque = np.asarray(torque, dtype=float).reshape(-1)
        if self.torque.shape != (model.nu,) or not np.all(np.isfinite(self.torque)):
            raise ValueError(f"torque must be {model.nu} finite numbers (one per actuator), got {torque!r}")
        # Generalized force of the torque: Σ_i gear_i · τ_i on actuator i's joint dofs.
        self._force = np.zeros(model.nv)
        for i in range(model.nu):
            if int(model.actuator_trntype[i]) != int(mujoco.mjtTrn.mjTRN_JOINT):
                raise ValueError(f"actuator {i} does not drive a joint")
            joint = int(model.actuator_trnid[i, 0])
            start = int(model.jnt_dofadr[joint])
            dofs = {int(mujoco.mjtJoint.mjJNT_HINGE): 1, int(mujoco.mjtJoint.mjJNT_SLIDE): 1,
                    int(mujoco.mjtJoint.mjJNT_BALL): 3}[int(model.jnt_type[joint])]
            self._force[start:start + dofs] += model.actuator_gear[i, :dofs] * self.torque[i]

    def _apply(self) -> None:
        self.env.unwrapped.data.qfrc_applied[:] = self._force

    def reset(self, **kwargs: Any):
        result = self.env.reset(**kwargs)
        self._apply()
        return result

    def step(self, action: Any):
        self._apply()
        return self.env.step(action)

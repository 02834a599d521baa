"""fvin_mpc — learned forced variational integrators on S³ (S3FVIN) for model-based control.

Layers, each importing only those above it in this list (``tests/test_layers.py`` reads the
imports and holds the line). Every module, one line each:

:mod:`fvin_mpc.core` — the math, written once for NumPy, torch and CasADi:

* ``space`` — the configuration spaces (S³, SO(3), R³ × S³): one value every layer carries — state
  layout, step, energy, learned terms, closed form, chart, check — and the registry that names them.
* ``blocks`` — a state as a product of blocks (hinge, slide, ball, free joint): the chart, check and distance
  written once per block kind for every backend.
* ``tree_dynamics`` — a MuJoCo model's kinematic tree in closed form: ``M(q)``, bias, passive forces and actuator
  moments.
* ``goals`` — what a scene's goal is (a pivot's upright orientation at rest, a craft's hover point).
* ``backend`` — the leaf operations that differ between NumPy, torch and CasADi (the only backend-specific code).
* ``s3`` — unit-quaternion algebra on S³ and 3×3 linear algebra.
* ``so3`` — the rotation group SO(3) on 3×3 matrices (for the SO3FVIN baseline).
* ``fvin`` — the forced S³ variational integrator step and its residual.
* ``fvin_r3s3`` — the R³ × S³ step: translation and rotation together.
* ``fvin_so3`` — the forced LieFVIN step on SO(3), the paper's baseline.
* ``mechanism_step`` — the forced variational step of a mechanism (a tree of joints) on the product of its blocks.
* ``networks`` — the learned S3FVIN terms ``J``, ``U``, ``g`` (and ``D``) from weights.
* ``networks_r3s3`` — the learned R³ × S³ terms ``M``, ``J``, ``U``, force and torque gains.
* ``networks_so3`` — the learned SO3FVIN terms.
* ``model_parameters`` — a model's run-time parameters (gain scales, explicit physical values) and the
  weights or body fields they stand in for.
* ``rigid_body`` — closed-form bodies on a fixed pivot, read off an MJCF.
* ``quadrotor`` — the closed-form quadrotor (R³ × S³) and a geometric controller.
* ``state`` — array checks at numeric boundaries.
* ``errors`` — the user-facing errors, one root every command reports as one line.
* ``checkpoint`` — safetensors weights + JSON sidecar; where the shipped checkpoints are.
* ``data`` — trajectory data sets of any configuration space (``.npz``), one container.

:mod:`fvin_mpc.envs` — Gymnasium environments over MuJoCo scenes (the repository's ``envs/`` folder,
installed under this name):

* ``scenes`` — the scene registry and physics declarations.
* ``rigid_body_env`` — one rigid body on one actuated hinge or ball joint.
* ``quadrotor_env`` — a free body with rotors (the ``quadrotor`` scene).
* ``pendulum_v1`` — conversions between Gymnasium's ``Pendulum-v1`` and the ``pendulum`` scene.
* ``disturbance`` — a known constant torque disturbance (the offset-free tests' oracle).
* ``joint_blocks`` — a MuJoCo model's joints as the blocks of a state (its ``qpos``, ``qvel``).
* ``mechanism_family`` — a seeded random family of mechanisms (cart-poles, double and rotary pendulums, ball
  arms) and the closed form's check against MuJoCo.
* ``families`` — seeded random scene families (hinge, ball) and what an MJCF has that the package cannot take.
* ``flyer_family`` — a seeded random family of free-flying crafts (rotor layouts, wrench actuators, drag).

:mod:`fvin_mpc.learning` — the only torch importers:

* ``collection`` — trajectories from a scene (``python -m fvin_mpc.collect``).
* ``excitation`` — a pivoted scene's default data: energy-pumping bursts sized from its scales.
* ``swing_measure`` — the model measure that predicts control: a full-torque swing, plant against model.
* ``free_body_excitation`` — free-body data from the MJCF alone: random-excitation bursts from random states.
* ``model`` — the trainable torch model, one shell parametrized by the configuration space (fast
  rollouts for S³ and SO(3)).
* ``space_training`` — what training does per space: settings, loss scales, the free body's report.
* ``training`` — one training loop for every model (``python -m fvin_mpc.train``).
* ``timing`` — torch-side thread and step-timing helpers (training; the repository's ``benchmarks/``).

:mod:`fvin_mpc.control` — the control runtime, no torch:

* ``model_export`` — a model's step as a CasADi function; the compile cache.
* ``problem`` — the one control problem both solvers solve: its residuals, bounds, references and
  disturbance estimate.
* ``mpc`` — the problem solved to convergence (IPOPT), with multi-start cold solves.
* ``presets`` — the built-in scenes' controller presets, each with its reason.
* ``family_filter`` — whether the closed-form controller swings a generated scene up (the family filter).
* ``rti`` — the real-time iteration MPC (any product of blocks): the controller.
* ``linearization`` — the real-time iteration's linearization: a stage's gap and ``[A B]`` in the blocks' charts,
  the trust region, the kept Jacobians.
* ``riccati_qp`` — the real-time iteration's QP solver: interior point on the input boxes, a Riccati recursion per
  iteration (its method and where it breaks).
* ``implicit_dynamics`` — the step's own equations as the real-time iteration's dynamics constraint.
* ``term_expansion`` — a model's terms expanded to first order where a stage is linearized (the same
  Jacobian in fewer operations).
* ``riccati_kernel`` — the Riccati stage of the generated QP as hand-written C (``c_kernels/``) for free bodies.
* ``lane_kernel`` — a stage function mapped over the horizon four stages at a time on the vector units (CasADi's
  C translated into vector code).
* ``buffered`` — CasADi calls through preallocated buffers, without per-call conversions.
* ``c_controller`` — the real-time loop as a self-contained C library (generated functions + C driver),
  and Python driving that library.
* ``energy_shaping`` — energy-shaping swing-up with an LQR catch from ``J``, ``U``, ``g``.
* ``closed_loop`` — closed-loop episodes (waiting or latency-aware) and their metrics.
* ``scene`` — a scene's env, model, MPC and settings (the one path every command takes).
* ``flight`` — the quadrotor's MPC settings, references and flight metrics.
* ``adaptation`` — a few physical parameters of a model (mass, actuator gains, damping) re-fitted online
  from a sliding window of transitions by Levenberg–Marquardt.

:mod:`fvin_mpc.studies` — evaluation, sweeps and reports:

* ``evaluation`` — closed-loop evaluation over seeded episodes.
* ``model_quality`` — a checkpoint's model quality: planar on a hinge, the recovered inertia on a ball joint.
* ``flight_report`` — the quadrotor's recovery and figure-eight study.
* ``training_sweep`` — training sweeps.
* ``learning_loop`` — learning in the loop: the learned controller gathers its model's data (excitation,
  train, evaluate, explore, retrain).
* ``pool`` — the one way to run many tasks (in order, process pool or Ray).
* ``starts`` — the episodes' initial conditions.
* ``report`` — the one report writer.

The commands, thin over the library (``python -m fvin_mpc.<name>``):

* ``swingup`` — swing a scene's body up with the MPC.
* ``fly`` — fly the quadrotor with the real-time MPC.
* ``collect`` — collect trajectories from a scene.
* ``train`` — train a model on trajectory data (needs the ``train`` extra: torch).
* ``export`` — write a checkpoint's step as a CasADi file, or a scene's real-time controller as a C library.
* ``evaluate`` — closed-loop evaluation of the controllers.
* ``quality`` — model quality of checkpoints (hinge or ball joint).
* ``sweep`` — a training sweep.
* ``learn`` — learn a scene's model in the loop (needs the ``train`` extra: torch).
* ``_cli`` — the command-line options the commands share.

The research studies (accuracy against time, the paper's figures, data efficiency, Pendulum-v1, the
ball joint) are not part of the package: they live in the repository's ``benchmarks/`` folder and run
from a clone (``python -m benchmarks <study>``; ``benchmarks/README.md``).

The shipped checkpoints are ``fvin_mpc.checkpoints`` (the repository's ``checkpoints/`` folder,
installed as package data).
"""

__version__ = "0.1.0"

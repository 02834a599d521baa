"""Bad inputs at the boundaries: NaN/inf or wrongly shaped actions and observations (env,
energy-shaping controller) and corrupted checkpoint files.

The MPC's own input checks are in ``test_hard_mpc.py``. Every rejection must be a clear
``ValueError`` (``CheckpointError`` for files) that changes nothing: no torque reaches MuJoCo.
"""

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import strategies as S
from hypothesis import given, settings
from hypothesis import strategies as st

from fvin_mpc.control.energy_shaping import EnergyShapingController
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from fvin_mpc.core.networks import ModelConfig, init_weights
from fvin_mpc.core.rigid_body import PENDULUM
from fvin_mpc.core.state import UNIT_NORM_TOLERANCE

NP = get_ops("numpy")


def bad_arrays(shape, low, high):
    """Non-finite arrays of the right shape, finite arrays of a wrong shape, or non-numbers."""
    return st.one_of(
        S.non_finite_arrays(shape, low, high),
        S.wrong_shapes(shape).map(lambda s: np.full(s, 0.5)),
        st.sampled_from([None, "1.0", [1.0, "a"], {"u": 1.0}, [[1.0], [2.0, 3.0]]]),
    )


# ----------------------------------------------------------------------------- env
@pytest.fixture(scope="module")
def envs_by_scene():
    from fvin_mpc.envs import RigidBodyEnv

    built = {}
    for scene in ("pendulum", "spherical_pendulum"):
        env = RigidBodyEnv(scene)
        env.reset(seed=0, options={"random": True, "max_omega": 2.0})
        built[scene] = env
    return built


@settings(max_examples=S.budget(500))
@given(scene=st.sampled_from(["pendulum", "spherical_pendulum"]), data=st.data())
@S.counted
def test_env_step_rejects_bad_actions_and_sends_nothing(envs_by_scene, scene, data):
    env = envs_by_scene[scene]
    action = data.draw(bad_arrays((env.model.nu,), -2.0, 2.0))
    ctrl, qpos, qvel, time = env.data.ctrl.copy(), env.data.qpos.copy(), env.data.qvel.copy(), env.data.time
    with pytest.raises(ValueError):
        env.step(action)
    np.testing.assert_array_equal(env.data.ctrl, ctrl)
    np.testing.assert_array_equal(env.data.qpos, qpos)
    np.testing.assert_array_equal(env.data.qvel, qvel)
    assert env.data.time == time


@settings(max_examples=S.budget(200))
@given(scene=st.sampled_from(["pendulum", "spherical_pendulum"]), data=st.data())
@S.counted
def test_env_set_state_rejects_bad_states_and_leaves_the_simulation(envs_by_scene, scene, data):
    env = envs_by_scene[scene]
    which = data.draw(st.sampled_from(["qpos", "qvel"]))
    good = {"qpos": env.data.qpos.copy(), "qvel": env.data.qvel.copy()}
    shape = {"qpos": (env.model.nq,), "qvel": (env.model.nv,)}[which]
    good[which] = data.draw(bad_arrays(shape, -1.0, 1.0))
    qpos, qvel = env.data.qpos.copy(), env.data.qvel.copy()
    with pytest.raises(ValueError):
        env.set_state(good["qpos"], good["qvel"])
    np.testing.assert_array_equal(env.data.qpos, qpos)
    np.testing.assert_array_equal(env.data.qvel, qvel)


# ----------------------------------------------------------------------------- energy shaping
@pytest.fixture(scope="module")
def energy_shaping():
    return EnergyShapingController(PENDULUM.terms(NP), 0.05, 3, np.array([0.0, 0.0, 1.0, 0.0]),
                                   np.array([-2.0]), np.array([2.0]), rest=np.array([1.0, 0.0, 0.0, 0.0]))


@settings(max_examples=S.budget(300))
@given(x=bad_arrays((7,), -10.0, 10.0))
@S.counted
def test_energy_shaping_rejects_bad_observations(energy_shaping, x):
    with pytest.raises(ValueError):
        energy_shaping(x)


@settings(max_examples=S.budget(300))
@given(q=S.unit_quaternions(), omega=S.vectors(3, -10.0, 10.0),
       norm=st.one_of(st.just(0.0), S.log_uniform(1e-8, 1e8), S.floats(1 - 3e-3, 1 + 3e-3)))
@S.counted
def test_energy_shaping_follows_the_unit_norm_policy(energy_shaping, q, omega, norm):
    """Same policy as the MPC (the space's ``check``): normalize within 1e-3 of unit
    norm, else ``ValueError`` — never a NaN torque (``q = 0``) or a torque for a non-rotation."""
    measured = norm * q
    off = abs(np.linalg.norm(measured) - 1.0)
    if abs(off - UNIT_NORM_TOLERANCE) < 1e-12:
        return
    energy_shaping.reset()
    if off <= UNIT_NORM_TOLERANCE:
        u, _ = energy_shaping(np.r_[measured, omega])
        energy_shaping.reset()
        u_unit, _ = energy_shaping(np.r_[q, omega])
        assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= 2.0)
        np.testing.assert_allclose(u, u_unit, atol=1e-9)
    else:
        with pytest.raises(ValueError):
            energy_shaping(np.r_[measured, omega])


# ----------------------------------------------------------------------------- corrupted checkpoints
@pytest.fixture(scope="module")
def saved_checkpoint(tmp_path_factory):
    config = ModelConfig(variant="sign-invariant", hidden_width=4)
    stem = save_checkpoint(tmp_path_factory.mktemp("ckpt") / "corrupt_me", config, init_weights(config, seed=2),
                           scene="pendulum", body="pole")
    original = load_checkpoint(stem)
    return stem, original


def corrupt(data: bytes, draw) -> tuple[bytes, str, list[int]]:
    kind = draw(st.sampled_from(["flip", "truncate"]))
    if kind == "truncate":
        length = draw(st.integers(0, len(data) - 1))
        return data[:length], kind, []
    positions = draw(st.lists(st.integers(0, len(data) - 1), min_size=1, max_size=3, unique=True))
    corrupted = bytearray(data)
    for p in positions:
        corrupted[p] ^= draw(st.integers(1, 255))
    return bytes(corrupted), kind, positions


def try_load(stem):
    """Load; any exception other than CheckpointError fails the test."""
    try:
        return load_checkpoint(stem), None
    except CheckpointError as error:
        return None, error


def same_weights(a, b) -> bool:
    return set(a) == set(b) and all(np.array_equal(a[k], b[k]) for k in a)


@settings(max_examples=S.budget(300))
@given(target=st.sampled_from(["safetensors", "json"]), data=st.data())
@S.counted
def test_corrupted_checkpoint_raises_checkpoint_error_or_loads_exactly_what_the_files_say(saved_checkpoint, target,
                                                                                          data):
    """Byte flips (1–3, random masks) and truncations of either file.

    The loader raises ``CheckpointError`` (never another exception) or returns exactly what the
    files say:

    * ``.safetensors``: the sidecar records the file's SHA-256, so every changed file is refused —
      truncated, header flipped, or a flip inside float data that still parses;
    * ``.json`` flips/truncations: ``CheckpointError``, or the config/metadata the corrupted JSON
      parses to, with the original weights; a JSON that parses to the original must load.
    """
    stem, original = saved_checkpoint
    path = stem.with_suffix(f".{target}")
    raw = path.read_bytes()
    corrupted, kind, positions = corrupt(raw, data.draw)
    workdir = Path(tempfile.mkdtemp(prefix="hard_ckpt_"))
    try:
        for suffix in (".safetensors", ".json"):
            shutil.copy(stem.with_suffix(suffix), workdir / f"c{suffix}")
        (workdir / f"c.{target}").write_bytes(corrupted)
        loaded, error = try_load(workdir / "c")
    finally:
        shutil.rmtree(workdir)

    if target == "safetensors":
        assert corrupted != raw and loaded is None and error is not None, f"a corrupted ({kind}) weights file loaded"
    else:
        try:
            parsed = json.loads(corrupted.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            parsed = None
        if parsed is None:
            assert error is not None, "an unparseable sidecar loaded"
            return
        if parsed == json.loads(raw):
            assert loaded is not None, f"a sidecar equal to the original was refused: {error}"
        if loaded is not None:
            assert same_weights(dict(loaded.weights), dict(original.weights))
            assert loaded.config.to_dict() == {**original.config.to_dict(), **parsed["model"]}
            assert dict(loaded.metadata) == {k: v for k, v in parsed.items() if k not in ("format", "model")}

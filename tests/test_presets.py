"""Controller presets live in ``control`` (not in the scene declarations), for built-in scenes only."""

from __future__ import annotations

import re
import shutil
from dataclasses import fields
from pathlib import Path

import pytest

from fvin_mpc.control.mpc import IpoptOptions, MPCSettings, RTIOptions
from fvin_mpc.control.presets import PRESETS, preset_for
from fvin_mpc.control.scene import default_mpc_settings, scene_mpc_settings, scene_scales
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.envs.scenes import SCENES, SceneSpec, resolve_scene

ROOT = Path(__file__).resolve().parents[1]
SETTING_NAMES = {f.name for f in fields(MPCSettings)}


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_names_real_settings_and_says_why_with_a_docs_page(name):
    preset = PRESETS[name]
    assert name in SCENES
    changed = set(preset.settings) | {key for fields_ in preset.per_solver.values() for key in fields_}
    assert changed and changed <= SETTING_NAMES
    assert set(preset.per_solver) <= {"ipopt", "sqpmethod", "fatrop", "rti"}
    # solver options live in the options objects, problem fields in settings / per_solver
    assert not {"ipopt", "rti"} & changed
    assert preset.ipopt is None or isinstance(preset.ipopt, IpoptOptions)
    assert preset.rti is None or isinstance(preset.rti, RTIOptions)
    assert preset.reasons
    for reason in preset.reasons:
        pages = re.findall(r"docs/[\w/.-]+\.md", reason)
        assert pages, reason
        assert all((ROOT / page).is_file() for page in pages), reason


def test_scene_declarations_carry_no_controller_settings():
    assert not {"mpc", "mpc_per_solver"} & {f.name for f in fields(SceneSpec)}


def test_the_built_in_scene_gets_its_preset_and_a_user_file_of_the_same_name_does_not(tmp_path):
    built_in = RigidBodyEnv(scene="spherical_pendulum")
    copy = tmp_path / "spherical_pendulum.xml"
    shutil.copy(resolve_scene("spherical_pendulum").xml_path, copy)
    user = RigidBodyEnv(scene=copy)
    try:
        assert preset_for(user.scene_spec).fields_for("rti") == {}
        derived = default_mpc_settings(scene_scales(user))
        assert scene_mpc_settings(user, solver="rti") == MPCSettings(**{**derived.__dict__, "solver": "rti"})
        rti = scene_mpc_settings(built_in, solver="rti")
        assert (rti.horizon, rti.rti.max_iter, rti.omega_weight) == (50, 3, 0.06)
        ipopt = scene_mpc_settings(built_in)
        scaled = default_mpc_settings(scene_scales(built_in)).omega_weight  # the RTI-only 0.06 stays out
        assert (ipopt.horizon, ipopt.terminal_energy_weight, ipopt.omega_weight) == (50, 0.0, scaled)
    finally:
        built_in.close()
        user.close()

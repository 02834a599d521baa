import os

# Headless rendering for every test that touches MuJoCo's renderer.
os.environ.setdefault("MUJOCO_GL", "egl")

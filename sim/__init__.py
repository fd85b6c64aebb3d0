"""The simulated tapecell: a MuJoCo model of the whole robot cell.

MuJoCo must render headless here (no display), so the EGL backend is chosen before
``mujoco`` is imported anywhere in this package.
"""
import os

os.environ.setdefault("MUJOCO_GL", "egl")

"""LIBERO environment layer: suites and tasks, env construction, robot features, rendering on the CPU."""

import os

# MuJoCo picks its GL backend at import time; Mesa's EGL renders on the CPU without a display.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

"""LIBERO environment layer: suites and tasks, env construction, robot features, rendering on the CPU."""

import contextlib
import logging
import os

# MuJoCo picks its GL backend at import time; Mesa's EGL renders on the CPU without a display.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
# No GPU visible (CUDA_VISIBLE_DEVICES='', as submitit's local launcher sets it): robosuite would pick its EGL device
# with int(''); EGL's first device (Mesa's, on the CPU) is what it picks when the variable is unset.
if os.environ.get("CUDA_VISIBLE_DEVICES") == "":
    os.environ.setdefault("MUJOCO_EGL_DEVICE_ID", "0")

# robosuite warns at import, in every worker, that it has no private macro file (three lines each); its defaults are
# the ones LIBERO expects, so that notice is dropped and its other warnings kept.
logging.getLogger("robosuite_logs").addFilter(lambda record: "macro" not in record.getMessage())

# The CUDA build of torch brings triton, which bundles its own LLVM and is imported lazily (torch._dynamo, e.g. on
# `import torchvision`). Loaded after Mesa's llvmpipe has made a GL context it segfaults the process; loaded first,
# both work.
with contextlib.suppress(ImportError):
    import triton  # noqa: F401

"""LIBERO environment layer: suites and tasks, env construction, robot features, rendering on the CPU."""

import contextlib
import os

# MuJoCo picks its GL backend at import time; Mesa's EGL renders on the CPU without a display.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

# The CUDA build of torch brings triton, which bundles its own LLVM and is imported lazily (torch._dynamo, e.g. on
# `import torchvision`). Loaded after Mesa's llvmpipe has made a GL context it segfaults the process; loaded first,
# both work.
with contextlib.suppress(ImportError):
    import triton  # noqa: F401

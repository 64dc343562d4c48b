import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
# Tests run tiny models: one torch thread is fastest, and the 2 cores are shared with simulators and other jobs.
os.environ.setdefault("OMP_NUM_THREADS", "1")

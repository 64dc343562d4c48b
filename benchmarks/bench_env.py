"""LIBERO env step and render timings on libero_spatial task 0 (CPU rendering through Mesa).

    python benchmarks/bench_env.py                      # the default preset (conf/env/fast.yaml)
    python benchmarks/bench_env.py --preset standard    # LIBERO's own rendering (conf/env/standard.yaml)
    python benchmarks/bench_env.py --against standard   # ... and, interleaved step by step, another preset
    python benchmarks/bench_env.py --compare            # ... and, interleaved step by step, MuJoCo's stock settings
    python benchmarks/bench_env.py msaa_samples=4 mesh_cell_mm=0 --steps 30   # any EnvConfig field

Each of --steps iterations takes a physics-only step, a step that renders both cameras, then renders each camera
once more on its own; the motion is a scripted back-and-forth of the end effector. Times are wall clock: on a
machine shared with other work, read the medians next to the load average printed in the header.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import vlactl.env  # noqa: E402,F401  (sets MUJOCO_GL before MuJoCo loads)

import numpy as np  # noqa: E402
import yaml  # noqa: E402

from vlactl.env.libero_env import CAMERAS, EnvConfig, LiberoEnv  # noqa: E402

SUITE, TASK = "libero_spatial", 0
# What LIBERO renders with out of the box (reflections stay off, as in the project since before these levers).
STOCK = {"msaa_samples": 4, "cull_offscreen": False, "mesh_cell_mm": 0.0}
PRESETS = Path(__file__).resolve().parents[1] / "conf" / "env"


def parse_overrides(items: list[str]) -> dict:
    fields = {f.name: f for f in dataclasses.fields(EnvConfig)}
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        if key not in fields or not _:
            sys.exit(f"error: expected FIELD=VALUE with FIELD one of {', '.join(fields)}; got {item!r}")
        out[key] = yaml.safe_load(value)
    return out


def action(i: int) -> np.ndarray:
    """Back and forth in x and y, up and down a little, gripper toggling every 20 steps."""
    phase = np.sin(2 * np.pi * i / 40)
    return np.array([0.4 * phase, -0.3 * phase, 0.2 * np.cos(2 * np.pi * i / 40), 0, 0, 0, 1 if (i // 20) % 2 else -1])


def measure(envs: dict[str, LiberoEnv], steps: int) -> dict[str, dict[str, list[float]]]:
    times = {name: {} for name in envs}

    def timed(name, key, fn):
        t = time.perf_counter()
        fn()
        times[name].setdefault(key, []).append((time.perf_counter() - t) * 1e3)

    for env in envs.values():
        env.reset(0, seed=0)
        for _ in range(3):  # warm-up: JIT-compiled shaders, first uploads
            env.step(action(0), render=True)
    for i in range(steps):
        for name, env in envs.items():  # interleaved, so load from other processes hits every variant alike
            timed(name, "physics-only step", lambda: env.step(action(2 * i), render=False))
            timed(name, "step + both images", lambda: env.step(action(2 * i + 1), render=True))
            ctx = env.env.sim._render_context_offscreen
            for cam in CAMERAS:
                timed(name, f"render {cam}", lambda: env._render_camera(ctx, cam))
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="EnvConfig FIELD=VALUE")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--preset", default="fast", help="conf/env/<preset>.yaml: fast or standard")
    parser.add_argument("--compare", action="store_true", help="also time MuJoCo's stock render settings")
    parser.add_argument("--against", help="also time this preset (unchanged by the overrides)")
    args = parser.parse_args()

    def preset(name: str) -> dict:
        return yaml.safe_load((PRESETS / f"{name}.yaml").read_text())

    cfg = EnvConfig(**{**preset(args.preset), **parse_overrides(args.overrides)})
    variants = {args.preset: cfg}
    if args.compare:
        variants["stock"] = dataclasses.replace(cfg, **STOCK)
    if args.against:
        variants[args.against] = EnvConfig(**preset(args.against))
    envs = {name: LiberoEnv(SUITE, TASK, c, render=True) for name, c in variants.items()}
    times = measure(envs, args.steps)

    gl = os.environ.get("MUJOCO_GL"), os.environ.get("LP_NUM_THREADS", "default")
    print(f"{SUITE} task {TASK}, {args.steps} iterations, MUJOCO_GL={gl[0]}, "
          f"LP_NUM_THREADS={gl[1]}, load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    for name, c in variants.items():
        keys = ("image_size", "msaa_samples", "cull_offscreen", "mesh_cell_mm", "reflections")
        shown = {k: getattr(c, k) for k in keys}
        print(f"  {name}: " + " ".join(f"{k}={v}" for k, v in shown.items()))
    header = f"{'ms':28s}" + "".join(f"{name + ' median':>16s}{name + ' p90':>13s}" for name in variants)
    print(header)
    for key in times[args.preset]:
        row = f"{key:28s}"
        for name in variants:
            v = times[name][key]
            row += f"{np.median(v):16.1f}{np.percentile(v, 90):13.1f}"
        print(row)
    for env in envs.values():
        env.close()


if __name__ == "__main__":
    main()

"""Wall time of a 2 x 2 `vlactl rollout -m` sweep under Hydra's default launcher (one run after another) and under
joblib (runs in parallel processes), with the tiny random model: 1 episode of a few steps per run, one simulator each.

    python benchmarks/bench_multirun.py [--steps 4] [--n-jobs 2]

Each launcher runs the same command in a fresh process into its own temporary folder; the runs are what a user gets
(the simulator's start-up dominates at this size, which is what the parallel launcher spreads over the cores).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def sweep(root: Path, steps: int, *launcher: str) -> float:
    command = [sys.executable, "-m", "vlactl.cli", "rollout", "-m", "model=random", "tasks=[0]", "episodes_per_task=1",
               f"max_steps={steps}", "workers=1", f"output_root={root / 'runs'}", "seed=0,1", "snap_gripper=true,false",
               f"hydra.sweep.dir={root / 'hydra'}", *launcher]
    start = time.perf_counter()
    subprocess.run(command, cwd=ROOT, check=True, capture_output=True)
    wall = time.perf_counter() - start
    assert len(list((root / "runs").iterdir())) == 4
    return wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--n-jobs", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        basic = sweep(Path(tmp) / "basic", args.steps)
        joblib = sweep(Path(tmp) / "joblib", args.steps, "hydra/launcher=joblib", f"hydra.launcher.n_jobs={args.n_jobs}")
    print(f"2 x 2 rollout sweep, {args.steps} steps per run: default launcher {basic:.1f} s, "
          f"joblib n_jobs={args.n_jobs} {joblib:.1f} s ({basic / joblib:.2f}x)")


if __name__ == "__main__":
    main()

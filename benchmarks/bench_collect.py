"""Peak memory of `vlactl collect` at two dataset sizes: it should stay flat (one shard and one batch group in memory,
images memory-mapped), not grow with the number of frames. Capture overhead per forward is in bench_policy.py.

    python benchmarks/bench_collect.py [--episodes 8 32] [--frames 40]

Each size runs in a fresh process on a synthetic LeRobot dataset with the default-size hybrid model (random weights;
memory does not depend on them), storing every layer in float32 with 256-frame shards.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

CHILD = """
import resource, sys, time
sys.path.insert(0, {bench!r})
from bench_policy import default_policy
from vlactl.config import load_policy_stage_config
from vlactl.steering.collect import run_collect
cfg = load_policy_stage_config("collect", ["model=hybrid", "dataset={dataset}", "output_dir={out}",
    "cache_dir={cache}", "dtype=float32", "shard_size=256", "threads=1"])
start = time.perf_counter()
run_collect(cfg, load_policy=lambda name: default_policy("hybrid"))
print(time.perf_counter() - start, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, nargs=2, default=[8, 32])
    parser.add_argument("--frames", type=int, default=40)
    args = parser.parse_args()
    from synthetic_demos import write_synthetic_demos

    print("episodes  frames  collect s  frames/s  peak RSS MB", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for episodes in args.episodes:
            dataset = write_synthetic_demos(Path(tmp) / f"demos{episodes}", episodes, args.frames)
            code = CHILD.format(bench=str(ROOT / "benchmarks"), dataset=dataset, out=Path(tmp) / f"acts{episodes}",
                                cache=Path(tmp) / "cache")
            result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
            seconds, peak = map(float, result.stdout.split()[-2:])
            frames = sum(args.frames + k for k in range(episodes))
            print(f"{episodes:8d}  {frames:6d}  {seconds:9.1f}  {frames / seconds:8.0f}  {peak:11.0f}", flush=True)


if __name__ == "__main__":
    main()

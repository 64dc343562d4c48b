"""Shards of a rollout: `shard=i num_shards=n` runs a fixed slice of the run's episodes, the merge joins them.

A shard runs in its own folder `<run>/shards/<i>-of-<n>/`, a run folder of its slice (config, parts/, tables), so two
shards never write the same file and one started with other settings stays out of the run until it is removed. The
merge copies every episode's part into the run's parts/ and writes the run's tables only once every episode of the
run is there; each file it writes is atomic and has the same content whoever writes it, so two shards finishing at
once and both merging is safe.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from vlactl.errors import UsageError
from vlactl.io import atomic_path
from vlactl.rollout import parts

_FOLDER = re.compile(r"(\d+)-of-(\d+)")


class Incomplete(UsageError):
    """Some of the run's episodes are finished in no folder yet, so the merge writes nothing."""


def check(shard, num_shards) -> None:
    def integer(value) -> bool:
        return isinstance(value, int) and not isinstance(value, bool)

    if not integer(num_shards) or num_shards < 1:
        raise UsageError(f"num_shards must be an integer >= 1, got {num_shards!r}")
    if not integer(shard) or not 0 <= shard < num_shards:
        raise UsageError(f"shard must be an integer in 0..{num_shards - 1} (num_shards={num_shards}), got {shard!r}")


def slice_of(keys: list[tuple[int, int]], shard: int, num_shards: int) -> list[tuple[int, int]]:
    """Round robin over the sorted (task, episode) keys: a function of the run's keys alone, so shards agree without
    talking, and each gets its share of every task (tasks differ in length)."""
    return sorted(keys)[shard::num_shards]


def folder(out: Path, shard: int, num_shards: int) -> Path:
    return out if num_shards == 1 else out / "shards" / f"{shard}-of-{num_shards}"


def folders(out: Path) -> list[Path]:
    """The run's shard folders that have started (hold a config), by shard count, then shard."""
    found = [p.parent for p in (out / "shards").glob("*-of-*/config.yaml") if _FOLDER.fullmatch(p.parent.name)]
    return sorted(found, key=lambda p: tuple(map(int, reversed(_FOLDER.fullmatch(p.name).groups()))))


def sources(out: Path, keys: list[tuple[int, int]], shard_folders: list[Path]) -> dict:
    """Per key, the folder holding its finished part: the run's own, else the first shard's that has it, else None."""
    return {key: next((f for f in [out, *shard_folders] if parts.is_done(f, *key)), None) for key in keys}


def adopt(out: Path, found: dict) -> None:
    """Copy the shards' parts (and videos) of `found` (`sources`) into the run folder, the row last as in
    `parts.write`, so the run folder resumes, merges and serves `judge_from` like one that ran in one process."""
    for (task, k), source in found.items():
        if source in (None, out):
            continue
        video = Path("videos") / f"task{task:02d}_ep{k:04d}.mp4"
        if (source / video).exists():
            _copy(source / video, out / video)
        src, dst = parts.stem(source, task, k), parts.stem(out, task, k)
        for suffix in (".parquet", ".json"):
            _copy(src.with_suffix(suffix), dst.with_suffix(suffix))


def _copy(src: Path, dst: Path) -> None:
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


def missing_line(out: Path, keys: list[tuple[int, int]], missing: list[tuple[int, int]], shown: int = 12) -> str:
    """One line: how many of the run's episodes are missing, which (task:episode), and, when the run was sharded
    one way, which shards owe them."""
    counts = {int(_FOLDER.fullmatch(f.name).group(2)) for f in folders(out)}
    listed = " ".join(f"{t}:{k}" for t, k in missing[:shown]) + (f" and {len(missing) - shown} more" if
                                                                  len(missing) > shown else "")
    line = f"{out} lacks {len(missing)} of {len(keys)} episodes (task:episode {listed})"
    if len(counts) == 1:
        n = counts.pop()
        order = {key: i for i, key in enumerate(sorted(keys))}
        owners = sorted({order[key] % n for key in missing})
        line += f"; re-run shard {', '.join(f'{i}-of-{n}' for i in owners)} with the same command"
    elif not counts:
        line += "; no shard has started in it: run them with shard=i num_shards=n"
    return line

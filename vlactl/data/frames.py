"""A LeRobot v3 demonstration dataset as in-memory arrays for training, images decoded once and cached.

The parquet files are read directly (faster than LeRobotDataset's per-frame access): PNG bytes are decoded once into
a uint8 array cached on disk as .npy, keyed by the dataset's fingerprint, and memory-mapped on later runs.
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlactl.data.lerobot_format import ACTION_KEY, STATE_KEY
from vlactl.errors import UsageError
from vlactl.io import atomic_path

IMAGE_PREFIX = "observation.images."


@dataclass
class Frames:
    images: np.ndarray  # uint8 [N, cams, H, W, 3], in the order of `cameras`
    state: np.ndarray  # float32 [N, 8]
    action: np.ndarray  # float32 [N, 7]
    episode: np.ndarray  # int64 [N]
    task: np.ndarray  # int64 [N], index into `tasks`
    tasks: list[str]
    fingerprint: str

    def __len__(self) -> int:
        return len(self.action)

    def images_at(self, index: np.ndarray) -> np.ndarray:
        """Images of the given frames, read from the cache file rather than through its mapping: pages read through
        a mapping stay in this process's memory, so one pass over the dataset (vlactl collect) would end up holding
        all of it. Runs of nearby frames are read in one go."""
        index = np.asarray(index)
        if not isinstance(self.images, np.memmap) or len(index) == 0:
            return np.asarray(self.images[index])
        order = np.argsort(index, kind="stable")
        wanted = index[order]
        shape, row = self.images.shape[1:], self.images[0].nbytes
        parts = []
        for run in np.split(wanted, np.flatnonzero(np.diff(wanted) > READ_GAP) + 1):
            first = int(run[0])
            span = np.fromfile(self.images.filename, np.uint8, (int(run[-1]) - first + 1) * row,
                               offset=self.images.offset + first * row)
            parts.append(span.reshape(-1, *shape)[run - first])
        out = np.empty((len(index), *shape), np.uint8)
        out[order] = np.concatenate(parts)
        return out

    def action_chunks(self, index: np.ndarray, chunk: int) -> tuple[np.ndarray, np.ndarray]:
        """Actions t..t+chunk-1 of each frame's episode [B, chunk, 7], and where they ran past its end [B, chunk]."""
        ahead = index[:, None] + np.arange(chunk)
        last = self._episode_last[index][:, None]
        return self.action[np.minimum(ahead, last)], ahead > last

    def __post_init__(self):
        ends = np.flatnonzero(np.diff(self.episode, append=-1))  # frames are stored episode by episode
        self._episode_last = np.repeat(ends, np.diff(np.concatenate([[-1], ends])))


IMAGE_BATCH = 256  # frames decoded at a time while building the image cache
READ_GAP = 8  # frames further apart than this are read separately (vlactl collect every=4 still reads runs)


def data_files(root: Path) -> list[Path]:
    files = sorted((root / "data").glob("chunk-*/file-*.parquet"))
    if not (root / "meta" / "info.json").is_file() or not files:
        raise UsageError(f"no LeRobot v3 dataset at {str(root)!r} (need meta/info.json and data/*/*.parquet)")
    return files


def fingerprint(root: Path) -> str:
    """Hash of the metadata and of each data file's name and size: cheap, and changes when episodes change."""
    h = hashlib.sha256()
    for path in sorted(p for p in (root / "meta").rglob("*") if p.is_file()):
        h.update(str(path.relative_to(root)).encode() + path.read_bytes())
    for path in data_files(root):
        h.update(f"{path.relative_to(root)}:{path.stat().st_size}".encode())
    return h.hexdigest()[:16]


def _column(table, key: str) -> np.ndarray:
    """A scalar column of a table or record batch -> [N]; a fixed-size list column (state, action) -> [N, size]."""
    import pyarrow as pa

    col = table[key]
    col = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    if pa.types.is_fixed_size_list(col.type):
        return col.flatten().to_numpy().reshape(len(col), col.type.list_size)
    return col.to_numpy()


def _decode(cells) -> np.ndarray:
    from PIL import Image

    return np.stack([np.asarray(Image.open(io.BytesIO(cell["bytes"])).convert("RGB")) for cell in cells])


def read_columns(root: Path, names: list[str]) -> dict[str, np.ndarray]:
    """Non-image columns of every frame, in LeRobot's global frame order (the row order of the image cache)."""
    import pyarrow.parquet as pq

    tables = [pq.read_table(f, columns=[*names, "index"], use_threads=False) for f in data_files(Path(root))]
    order = np.argsort(np.concatenate([_column(t, "index") for t in tables]), kind="stable")
    return {name: np.concatenate([_column(t, name) for t in tables])[order] for name in names}


def load_frames(root: Path, cameras: tuple[str, ...], cache_dir: Path, progress=None) -> Frames:
    import pyarrow.parquet as pq

    root = Path(root)
    files = data_files(root)
    info = json.loads((root / "meta" / "info.json").read_text())
    key = fingerprint(root)
    cache = Path(cache_dir) / f"frames-{key}"
    columns = read_columns(root, [STATE_KEY, ACTION_KEY, "episode_index", "task_index"])

    def column(name, dtype):
        return columns[name].astype(dtype)

    n = int(info["total_frames"])
    image_file = cache / ("images-" + "-".join(cameras) + ".npy")
    if not image_file.exists():
        size = info["features"][IMAGE_PREFIX + cameras[0]]["shape"]
        with atomic_path(image_file) as tmp:
            np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=(n, len(cameras), *size)).flush()
            done = 0
            # Batch by batch, each through a mapping dropped after it, so the whole decoded set is never held at once.
            # One reader thread: with Arrow's thread pool each new file left tens of MB behind in per-thread
            # allocator caches, and the peak grew with the number of files (README, measured).
            read = [IMAGE_PREFIX + c for c in cameras] + ["index"]
            for f in files:
                batches = pq.ParquetFile(f).iter_batches(batch_size=IMAGE_BATCH, columns=read, use_threads=False)
                for batch in batches:
                    rows = _column(batch, "index")  # LeRobot's global frame index: the row in the cache
                    out = np.load(tmp, mmap_mode="r+")
                    for k, cam in enumerate(cameras):
                        out[rows, k] = _decode(batch[IMAGE_PREFIX + cam].to_pylist())
                    out.flush()
                    del out
                    done += len(rows)
                    if progress is not None:
                        progress(done, n)
    tasks = pq.read_table(root / "meta" / "tasks.parquet").to_pandas()
    names = [name for name, _ in sorted(zip(tasks.index, tasks["task_index"]), key=lambda pair: pair[1])]
    return Frames(
        images=np.load(image_file, mmap_mode="r"),
        state=column(STATE_KEY, np.float32),
        action=column(ACTION_KEY, np.float32),
        episode=column("episode_index", np.int64),
        task=column("task_index", np.int64),
        tasks=names,
        fingerprint=key,
    )

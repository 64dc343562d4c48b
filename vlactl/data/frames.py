"""A LeRobot v3 demonstration dataset as in-memory arrays for training, images decoded once and cached.

The parquet files are read directly (faster than LeRobotDataset's per-frame access): the cameras, stored as images
(PNG bytes in the parquet files) or as video (LeRobot's default, MP4 files under videos/), are decoded once, resized
to the size the model takes, into a uint8 array cached on disk as .npy, keyed by the dataset's fingerprint, and
memory-mapped on later runs.
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlactl.data.lerobot_format import ACTION_DIM, ACTION_KEY, STATE_DIM, STATE_KEY
from vlactl.errors import UsageError
from vlactl.io import atomic_path

IMAGE_PREFIX = "observation.images."
CAMERA_DTYPES = ("image", "video")
BOOKKEEPING = ("timestamp", "frame_index", "episode_index", "index", "task_index")  # LeRobot's own columns


@dataclass
class Frames:
    images: np.ndarray  # uint8 [N, cams, H, W, 3], in the order of `cameras`
    state: np.ndarray  # float32 [N, 8]
    action: np.ndarray  # float32 [N, 7]
    episode: np.ndarray  # int64 [N]
    task: np.ndarray  # int64 [N], index into `tasks`
    tasks: list[str]
    fingerprint: str
    cameras: tuple[str, ...]

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
        raise UsageError(f"no LeRobot v3 dataset at {str(root)!r} (need meta/info.json and data/*/*.parquet); "
                         "make one with `vlactl demos` (the libero_spatial set, 10 tasks x 50: about 50 min on 2 cores)")
    return files


def fingerprint(root: Path) -> str:
    """Hash of the metadata and of each data and video file's name and size: cheap, and changes when episodes
    change."""
    h = hashlib.sha256()
    for path in sorted(p for p in (root / "meta").rglob("*") if p.is_file()):
        h.update(str(path.relative_to(root)).encode() + path.read_bytes())
    for path in data_files(root) + sorted((root / "videos").glob("*/chunk-*/file-*.mp4")):
        h.update(f"{path.relative_to(root)}:{path.stat().st_size}".encode())
    return h.hexdigest()[:16]


def check_readable(root: Path, features: dict, cameras: tuple[str, ...], state_dim: int) -> None:
    """One line naming the keys a dataset has and those the model needs, when it lacks one."""
    need = {**{IMAGE_PREFIX + cam: None for cam in cameras}, STATE_KEY: state_dim, ACTION_KEY: ACTION_DIM}

    def fits(key: str, size: int | None) -> bool:
        feature = features.get(key)
        if feature is None:
            return False
        return feature["dtype"] in CAMERA_DTYPES if size is None else list(feature["shape"]) == [size]

    def show(key: str, feature: dict) -> str:
        return f"{key} ({feature['dtype']})" if feature["dtype"] in CAMERA_DTYPES else f"{key} {list(feature['shape'])}"

    if not all(fits(key, size) for key, size in need.items()):
        found = ", ".join(show(k, f) for k, f in features.items() if k not in BOOKKEEPING)
        needed = ", ".join(f"{k} (image or video)" if size is None else f"{k} [{size}]" for k, size in need.items())
        raise UsageError(f"the model cannot read {str(root)!r}: it has {found}; the model needs {needed}")


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


def _fit(images: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Images [B, H, W, 3] at the cache's (H, W): resized (bilinear, antialiased) as a VLA's processor resizes."""
    if images.shape[1:3] == tuple(shape):
        return images
    from PIL import Image

    return np.stack([np.asarray(Image.fromarray(im).resize(shape[::-1], Image.BILINEAR)) for im in images])


def _image_batches(files: list[Path], key: str):
    """(rows, images) of a camera stored as images, IMAGE_BATCH frames at a time."""
    import pyarrow.parquet as pq

    # One reader thread: with Arrow's thread pool each new file left tens of MB behind in per-thread allocator
    # caches, and the peak grew with the number of files (README, measured).
    for f in files:
        for batch in pq.ParquetFile(f).iter_batches(batch_size=IMAGE_BATCH, columns=[key, "index"], use_threads=False):
            yield _column(batch, "index"), _decode(batch[key].to_pylist())  # index: LeRobot's global frame index


def _video_batches(root: Path, info: dict, key: str):
    """(rows, images) of a camera stored as video, each MP4 file decoded once from its start.

    Frame t of an episode is the video frame at the episode's `from_timestamp` + t's `timestamp`, the frame LeRobot's
    decode_video_frames returns. That function itself cannot run here: its pyav backend reads through
    torchvision.io.VideoReader, which torchvision 0.29 removed, and torchcodec needs FFmpeg's shared libraries; pyav
    (LeRobot's own encoder and bundled libav) decodes the same frames.
    """
    import av
    import pandas as pd
    import pyarrow.parquet as pq

    fps = info["fps"]
    chunk, file, start = (f"videos/{key}/{name}" for name in ("chunk_index", "file_index", "from_timestamp"))
    meta = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    episodes = pd.concat([pq.read_table(f, columns=["episode_index", chunk, file, start]).to_pandas() for f in meta])
    frames = read_columns(root, ["episode_index", "timestamp"])  # rows in LeRobot's global frame order
    begin = episodes.set_index("episode_index")[start].reindex(frames["episode_index"]).to_numpy()
    slots = np.round((begin + frames["timestamp"].reshape(-1)) * fps).astype(np.int64)
    for (c, f), group in episodes.groupby([chunk, file]):
        path = root / info["video_path"].format(video_key=key, chunk_index=int(c), file_index=int(f))
        rows = np.flatnonzero(np.isin(frames["episode_index"], group["episode_index"]))
        wanted = dict(zip(slots[rows].tolist(), rows.tolist()))
        found, images = [], []
        try:
            with av.open(str(path)) as container:
                for frame in container.decode(video=0):
                    row = wanted.pop(round(frame.time * fps), None)
                    if row is not None:
                        found.append(row)
                        images.append(frame.to_ndarray(format="rgb24"))
                    if len(found) == IMAGE_BATCH or (found and not wanted):
                        yield np.array(found), np.stack(images)
                        found, images = [], []
                    if not wanted:
                        break
        except (av.FFmpegError, OSError) as error:
            raise UsageError(f"cannot decode {str(path)!r} ({key}): {error}") from None
        if wanted:
            slot, row = min(wanted.items())
            raise UsageError(f"{str(path)!r} has no frame at {slot / fps:.3f} s (episode "
                             f"{frames['episode_index'][row]}): the video is shorter than its episodes")


def read_columns(root: Path, names: list[str]) -> dict[str, np.ndarray]:
    """Non-image columns of every frame, in LeRobot's global frame order (the row order of the image cache)."""
    import pyarrow.parquet as pq

    tables = [pq.read_table(f, columns=[*names, "index"], use_threads=False) for f in data_files(Path(root))]
    order = np.argsort(np.concatenate([_column(t, "index") for t in tables]), kind="stable")
    return {name: np.concatenate([_column(t, name) for t in tables])[order] for name in names}


def load_frames(root: Path, cameras: tuple[str, ...], cache_dir: Path, image_size: int | None = None,
                state_dim: int = STATE_DIM, progress=None) -> Frames:
    """The dataset's frames with these cameras' images at image_size x image_size (None: as the first camera is
    stored); a dataset without those cameras or with another state or action size is a UsageError."""
    import pyarrow.parquet as pq

    root = Path(root)
    cameras = tuple(cameras)
    files = data_files(root)
    info = json.loads((root / "meta" / "info.json").read_text())
    features = info["features"]
    check_readable(root, features, cameras, state_dim)
    key = fingerprint(root)
    cache = Path(cache_dir) / f"frames-{key}"
    columns = read_columns(root, [STATE_KEY, ACTION_KEY, "episode_index", "task_index"])

    def column(name, dtype):
        return columns[name].astype(dtype)

    n = int(info["total_frames"])
    stored = {cam: tuple(features[IMAGE_PREFIX + cam]["shape"][:2]) for cam in cameras}
    shape = (image_size, image_size) if image_size else stored[cameras[0]]
    resized = "" if all(size == shape for size in stored.values()) else f"-{shape[0]}x{shape[1]}"
    image_file = cache / ("images-" + "-".join(cameras) + resized + ".npy")
    if not image_file.exists():
        with atomic_path(image_file) as tmp:
            np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=(n, len(cameras), *shape, 3)).flush()
            done = 0
            for k, cam in enumerate(cameras):
                feature = IMAGE_PREFIX + cam
                video = features[feature]["dtype"] == "video"
                # Batch by batch, each through a mapping dropped after it, so the whole decoded set is never held.
                for rows, images in _video_batches(root, info, feature) if video else _image_batches(files, feature):
                    out = np.load(tmp, mmap_mode="r+")
                    out[rows, k] = _fit(images, shape)
                    out.flush()
                    del out
                    done += len(rows)
                    if progress is not None:
                        progress(done, n * len(cameras))
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
        cameras=cameras,
    )

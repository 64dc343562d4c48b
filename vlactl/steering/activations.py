"""The activation store that `vlactl collect` writes and the probe and steering stages read (docs/formats.md).

    <folder>/meta.json                          what is in the folder; the commit record, written last
    <folder>/labels.parquet                     one row per frame: episode, task, SPEC.md §2 state/action features
    <folder>/layers/<layer>/shard_00000.npy     [frames, width] pooled representation, float16 or float32

Frames are committed in whole shards. A shard's arrays are written first (temporary file, then rename), then the
labels, then meta.json; only shards that meta.json lists exist for a reader. An interrupted writer therefore leaves
at worst files past the commit point, which the next writer overwrites: re-opening the folder resumes it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Mapping

import numpy as np
import pandas as pd
import torch

from vlactl.env.features import ACTION_FEATURES, STATE_FEATURES
from vlactl.errors import UsageError
from vlactl.io import atomic_path, atomic_write_json, atomic_write_parquet

FORMAT, VERSION = "vlactl.activations", 1
FEATURES = (*STATE_FEATURES, *ACTION_FEATURES, "speed")  # SPEC.md §2, the probes' targets
LABEL_COLUMNS = ("episode", "frame_index", "task_id", "init_state", "instruction", *FEATURES)
DTYPES = ("float16", "float32")


def _shard_path(folder: Path, layer: str, index: int) -> Path:
    return folder / "layers" / layer / f"shard_{index:05d}.npy"


def _read_meta(folder: Path) -> dict:
    path = folder / "meta.json"
    if not path.is_file():
        raise UsageError(f"{str(folder)!r} is not an activation folder (no meta.json); pass activations=<folder> or "
                         "write one with `vlactl collect` (the libero_spatial demo set, every=4: about 10 min on 2 "
                         "cores)")
    meta = json.loads(path.read_text())
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise UsageError(
            f"{str(folder)!r} holds {meta.get('format')!r} version {meta.get('version')!r}; "
            f"this vlactl reads {FORMAT!r} version {VERSION}"
        )
    return meta


class ActivationWriter:
    """Appends frames (whole episodes, ideally) to an activation folder, one shard at a time; resumes an existing one.

    `append` buffers; a shard is written once `shard_size` frames are buffered, and by `flush` / `close`. Memory holds
    at most one shard plus one appended chunk.
    """

    def __init__(
        self, folder: Path, *, model: str, layers: list[str], widths: Mapping[str, int], pooling: str,
        dtype: str = "float16", shard_size: int = 4096, info: dict | None = None,
    ):
        if dtype not in DTYPES:
            raise UsageError(f"unknown activation dtype {dtype!r}; allowed: {', '.join(DTYPES)}")
        bad = [name for name in layers if "/" in name or name in ("", ".", "..")]
        if bad:
            raise ValueError(f"layer names must be usable as folder names, got {bad}")
        self.folder = Path(folder)
        wanted = {
            "format": FORMAT, "version": VERSION, "model": model, "pooling": pooling, "layers": list(layers),
            "widths": {name: int(widths[name]) for name in layers}, "dtype": dtype, "shard_size": int(shard_size),
        }
        if (self.folder / "meta.json").exists():
            self.meta = _read_meta(self.folder)
            clash = [key for key, value in wanted.items() if key != "shard_size" and self.meta.get(key) != value]
            if clash:
                key = clash[0]
                raise UsageError(
                    f"{str(self.folder)!r} already holds activations with {key}={self.meta.get(key)!r}, not "
                    f"{wanted[key]!r}; use another output folder"
                )
            labels = pd.read_parquet(self.folder / "labels.parquet") if self.meta["n_frames"] else None
            self._labels = labels.iloc[: self.meta["n_frames"]] if labels is not None else None
        else:
            self.meta = {**wanted, "shards": [], "n_frames": 0, "info": info or {}}
            self._labels = None
            atomic_write_json(self.folder / "meta.json", self.meta)
        self._chunks: list[tuple[dict[str, np.ndarray], pd.DataFrame]] = []
        self._buffered = 0

    @property
    def n_frames(self) -> int:
        """Frames committed so far (buffered ones not included)."""
        return self.meta["n_frames"]

    def episodes(self) -> set[int]:
        """Episodes with committed frames: what a resumed `collect` can skip."""
        return set() if self._labels is None else set(self._labels["episode"].unique().tolist())

    def append(self, activations: Mapping[str, np.ndarray], labels: pd.DataFrame) -> None:
        """activations: layer -> [n, width] pooled vectors; labels: n rows with at least LABEL_COLUMNS."""
        missing = [c for c in LABEL_COLUMNS if c not in labels.columns]
        if missing:
            raise ValueError(f"labels lack columns {missing}")
        chunk = {}
        for name in self.meta["layers"]:
            with np.errstate(over="ignore"):  # overflow shows up as inf, refused just below
                arr = np.asarray(activations[name]).astype(self.meta["dtype"], copy=False)
            expected = (len(labels), self.meta["widths"][name])
            if arr.shape != expected:
                raise ValueError(f"layer {name}: got shape {arr.shape}, expected {expected}")
            if not np.isfinite(arr).all():
                raise ValueError(f"layer {name}: non-finite values (beyond {self.meta['dtype']}'s range? use float32)")
            chunk[name] = arr
        self._chunks.append((chunk, labels.reset_index(drop=True)))
        self._buffered += len(labels)
        if self._buffered >= self.meta["shard_size"]:
            self.flush()

    def flush(self) -> None:
        """Commit everything buffered as one shard."""
        if not self._buffered:
            return
        index = len(self.meta["shards"])
        for name in self.meta["layers"]:
            with atomic_path(_shard_path(self.folder, name, index)) as tmp, open(tmp, "wb") as fh:
                np.save(fh, np.concatenate([chunk[name] for chunk, _ in self._chunks]))
        new = pd.concat([labels for _, labels in self._chunks], ignore_index=True)
        self._labels = new if self._labels is None else pd.concat([self._labels, new], ignore_index=True)
        atomic_write_parquet(self.folder / "labels.parquet", self._labels)
        self.meta["shards"].append(self._buffered)
        self.meta["n_frames"] += self._buffered
        atomic_write_json(self.folder / "meta.json", self.meta)  # the commit point
        self._chunks, self._buffered = [], 0

    def close(self) -> None:
        self.flush()

    def __enter__(self) -> "ActivationWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()  # appended chunks are complete, so committing them is safe even after an error


class ActivationStore:
    """Read side: metadata, labels, and [L, N, d] tensors of chosen layers read shard by shard from memory maps."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.meta = _read_meta(self.folder)
        self.model: str = self.meta["model"]
        self.pooling: str = self.meta["pooling"]
        self.layers: list[str] = list(self.meta["layers"])
        self.widths: dict[str, int] = dict(self.meta["widths"])
        self.n_frames: int = self.meta["n_frames"]
        # folders collected before the model said which layers can move its actions: all of them
        self.steerable: list[str] = list(self.meta["info"].get("steerable_layers", self.layers))

    @property
    def labels(self) -> pd.DataFrame:
        if not self.n_frames:
            return pd.DataFrame(columns=list(LABEL_COLUMNS))
        return pd.read_parquet(self.folder / "labels.parquet").iloc[: self.n_frames].reset_index(drop=True)

    def load(self, layers: list[str] | None = None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """[L, N, d] for `layers` (default: all), which must share one width."""
        layers = list(self.layers if layers is None else layers)
        unknown = [name for name in layers if name not in self.widths]
        if unknown:
            raise UsageError(f"unknown layer {unknown[0]!r}; this activation folder has: {', '.join(self.layers)}")
        widths = {self.widths[name] for name in layers}
        if len(widths) > 1:
            raise ValueError(f"layers {layers} have different widths {sorted(widths)}; load them separately")
        out = torch.empty(len(layers), self.n_frames, widths.pop() if widths else 0, dtype=dtype)
        for i, name in enumerate(layers):
            start = 0
            for index, count in enumerate(self.meta["shards"]):
                shard = np.load(_shard_path(self.folder, name, index), mmap_mode="r")
                out[i, start : start + count] = torch.from_numpy(np.array(shard))  # one shard in memory at a time
                start += count
        return out

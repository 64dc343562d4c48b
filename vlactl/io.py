"""File writing that never leaves a half-written result: write to a temporary sibling, then rename."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

from vlactl.errors import UsageError

_UMASK = os.umask(0o022)
os.umask(_UMASK)


@contextmanager
def atomic_path(path: Path):
    """Yield a temporary path beside `path`; it replaces `path` only if the block finishes without error."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp makes it owner-only; results are for everyone who may read the folder
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_json(path: Path, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, default=str) + "\n")


def atomic_write_parquet(path: Path, df) -> None:
    with atomic_path(path) as tmp:
        df.to_parquet(tmp, index=False)


def ensure_writable_dir(path: Path, requested: Path | None = None, key: str = "output_dir") -> Path:
    """Create `path` if needed and check that we can write there; a UsageError naming `requested` and the config
    `key` that sets it otherwise."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = tempfile.NamedTemporaryFile(dir=path, prefix=".write-test-", delete=True)
        probe.close()
    except OSError as exc:
        shown = str(requested or path)
        raise UsageError(f"output folder {shown!r} is not writable ({exc.strerror}); choose another with {key}=...") from None
    return path


@contextmanager
def atomic_dir(path: Path):
    """Yield a temporary folder beside `path` that replaces the folder `path` only if the block finishes.

    A folder cannot be swapped in one rename: the old one is moved aside first and deleted after, so a crash in
    between leaves `path` missing (never half-written) with the previous version beside it as `.<name>.old`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    tmp.chmod(0o755)  # mkdtemp makes it owner-only; a checkpoint is for everyone who may read the folder
    old = path.with_name(f".{path.name}.old")
    try:
        yield tmp
        shutil.rmtree(old, ignore_errors=True)
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def keyed_parts(out: Path, key: dict, results: tuple[str, ...]) -> Path:
    """`<out>/parts`, where a stage keeps each finished piece of its work for an interrupted run to resume from.
    `key` (JSON) is what the pieces were computed from; when it differs from the one they were made with, the pieces
    and the earlier run's `results` (names in `out`) are removed first, so a folder never mixes two runs."""
    digest = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()
    parts = Path(out) / "parts"
    if not (parts / "key").is_file() or (parts / "key").read_text() != digest:
        for name in (*results, "parts"):
            target = Path(out) / name
            shutil.rmtree(target) if target.is_dir() else target.unlink(missing_ok=True)
    parts.mkdir(parents=True, exist_ok=True)
    atomic_write_text(parts / "key", digest)
    return parts


def folder_name(text: str) -> str:
    """`text` made safe as one folder name: runs of other characters become '-' (e.g. `gripper=open` -> `gripper-open`)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-.")


def concat_tables(tables: list, empty_columns: list[str] | None = None):
    """Row-wise concatenation in which a table's all-missing column (the probe readings of an episode in which the
    controller never pushed, a control run's columns beside a filter run's) does not decide that column's dtype;
    columns in first-seen order."""
    import pandas as pd

    if not tables:
        return pd.DataFrame(columns=empty_columns)
    columns = list(dict.fromkeys(c for t in tables for c in t.columns))
    return pd.concat([t.dropna(axis=1, how="all") for t in tables], ignore_index=True).reindex(columns=columns)

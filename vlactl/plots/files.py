"""What every `vlactl plot` command shares: the run folder it draws from, the formats allowed, atomic saving."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display on these machines
import matplotlib.pyplot as plt  # noqa: E402

from vlactl.config import stage_output  # noqa: E402
from vlactl.errors import UsageError  # noqa: E402
from vlactl.io import atomic_path  # noqa: E402

FORMATS = ("png", "pdf")


def check_formats(formats) -> None:
    unknown = [f for f in formats if f not in FORMATS]
    if unknown:
        raise UsageError(f"unknown format {unknown[0]!r}; allowed: {', '.join(FORMATS)}")


def plotted_run(cfg, marker: str, kind: str, command: str) -> Path:
    """`run_dir=`, the folder a stage wrote (its `marker` file present), checked with the formats before any drawing."""
    if cfg.run_dir is None:
        raise UsageError(f"which {kind}? pass run_dir=<folder written by `{command}`>")
    check_formats(cfg.formats)
    return stage_output(cfg.run_dir, marker, kind, command)


def save_figure(fig, out: Path, name: str, formats, dpi) -> list[Path]:
    paths = []
    for fmt in formats:
        with atomic_path(out / f"{name}.{fmt}") as tmp:
            fig.savefig(tmp, format=fmt, dpi=dpi)
        paths.append(out / f"{name}.{fmt}")
    plt.close(fig)
    return paths
